"""bench/web.py --part bytes: the bytes a frame of each web stream against the PSNR of the held-out
camera's ground truth, measured from the browser's own pixels (issue 50 item 2).

Route (a), the model stream (``--web-stream model``): float32, float16 and int8 exports, each
decoded by the page on its (software) GPU. Route (b), the Gaussian chunk stream: the export at its
settings, then its chunks rewritten leaner, each still a valid chunk the page plays: Gaussians
below an opacity dropped, and positions and colours on coarser steps (the low bits of every u16
position and u8 colour zeroed). Every point's PSNR comes from the page's canvas. The reference is
atgs-eval's PSNR of the same checkpoint on the same frames and camera (the torch decode and the
reference rasterizer); each point also gives the page's PSNR against atgs-view's render of the same
view (the page must stay within 35 dB of it on every frame)."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import numpy as np

from atgs.web.browser import PlayerPage, chromium, serving

MODEL_PRECISIONS = ("float32", "float16", "int8")
OPACITY_CUTS = (0.02, 0.05)
COARSE = ((4, 1), (6, 2))  # (position bits dropped of 16, colour bits dropped of 8)


def _stream_bytes(web: Path) -> int:
    man = json.loads((web / "stream" / "manifest.json").read_text())
    files = man["model"]["parts"] if man.get("kind") == "model" else man["chunks"]
    return sum(f["bytes"] for f in files)


def _rewrite_chunks(src: Path, dst: Path, opacity_cut: float = 0.0, coarse: tuple[int, int] = (0, 0)) -> None:
    """A copy of the Gaussian export ``src`` whose chunks drop Gaussians below ``opacity_cut`` in
    the frames where they are, or keep ``16 - coarse[0]`` position bits and ``8 - coarse[1]``
    colour bits (rounded)."""
    from atgs.web.stream_format import (QuantizedChunk, Records, StreamFrame, decode_chunk, encode_chunk,
                                        pack_chunk)

    shutil.copytree(src, dst)
    man_path = dst / "stream" / "manifest.json"
    man = json.loads(man_path.read_text())
    for entry in man["chunks"]:
        path = dst / "stream" / entry["file"]
        c = decode_chunk(path.read_bytes())
        if opacity_cut > 0:
            ids = np.arange(c.gaussians)
            frames = []
            for fr in c.frames:
                keep = fr.opacities >= max(opacity_cut, 1e-9)
                frames.append(StreamFrame(ids[keep], fr.means[keep], fr.scales[keep], fr.quats[keep],
                                          fr.opacities[keep], fr.colors[keep]))
            data = encode_chunk(frames)
        else:
            def coarser(a: np.ndarray, bits: int, top: int) -> np.ndarray:
                step = 1 << bits
                return np.minimum(np.rint(a.astype(np.int64) / step) * step, top).astype(a.dtype)

            rec = [fr.records for fr in c.frames]
            stack = lambda name: np.stack([getattr(r, name) for r in rec])  # noqa: E731
            records = Records(coarser(stack("position"), coarse[0], 0xFFFF), stack("log_scale"), stack("rotation"),
                              stack("opacity"), coarser(stack("colour"), coarse[1], 0xFF))
            q = QuantizedChunk(np.arange(c.gaussians), c.static, records, c.position_min, c.position_max,
                               np.float32(c.log_scale_lo), np.float32(c.log_scale_hi))
            data = pack_chunk(q)
        path.write_bytes(data)
        g = decode_chunk(data)
        entry.update(bytes=len(data), gaussians=g.gaussians, static=g.static)
    man_path.write_text(json.dumps(man))


def _browser_psnr(browser, web: Path, camera: int, frames: list[int], truth: dict[int, np.ndarray],
                  view: dict[int, np.ndarray], psnr) -> tuple[list[float], list[float], float, dict]:
    """PSNR of the page's canvas against the ground truth and against atgs-view at each frame;
    seconds per seek; and per seek its seconds and, for a model stream, the page's own times of
    the frame it decoded (model_stream.js lastDecode: the GPU passes with the read-back, and the
    frame object the renderer takes)."""
    out, against_view, times = [], [], {"seek_s": [], "decode_ms": [], "prepare_ms": []}
    with serving(web) as url:
        page = PlayerPage(browser, url, {"camera": camera, "paused": 1, "size": "camera"}, timeout_s=900)
        page.first_frame()
        t0 = time.perf_counter()
        for f in frames:
            t = time.perf_counter()
            page.seek(f)
            got = page.pixels()
            times["seek_s"].append(time.perf_counter() - t)
            last = page.state().get("lastDecode")
            if last is not None:  # frame 0's decode came with the first frame (and the decoder's set-up)
                times["decode_ms"].append(last["decodeMs"])
                times["prepare_ms"].append(last["prepareMs"])
            out.append(psnr(got, truth[f]))
            against_view.append(psnr(got, view[f]))
        seek_s = (time.perf_counter() - t0) / max(len(frames), 1)
        page.close()
    return out, against_view, seek_s, times


def bytes_curve(ckpt: Path, scene_dir: Path | None, count: int, tmp: Path, export, desktop, psnr,
                routes: tuple[str, ...] = ("a", "b")) -> dict:
    """Every point of the curve: {route, variant, bytes_per_frame, psnr_db (mean), per_frame, ...};
    ``export(ckpt, out, args)`` runs atgs-export, ``desktop(ckpt, camera, frame, png)`` atgs-view;
    ``routes``: the routes measured ("a" the model stream, "b" the Gaussian chunks)."""
    from atgs.checkpoint import load_model, read_checkpoint
    from atgs.data.scene import PreparedScene
    from atgs.eval.evaluate import EvalConfig, evaluate

    data_dir = scene_dir or Path(read_checkpoint(ckpt).get("data_dir") or "")
    scene = PreparedScene.load(data_dir)
    model = load_model(ckpt)
    held = model.test_camera_names[0]
    camera = [c.name for c in model.cameras].index(held)
    scene_cam = [c.name for c in scene.cameras].index(held)
    n = model.num_frames
    frames = sorted({round(k * (n - 1) / max(count - 1, 1)) for k in range(count)})
    truth = {f: np.asarray(scene.image(scene_cam, f), np.float32) for f in frames}
    ev = evaluate(model, scene, EvalConfig(frames=tuple(frames), cameras=(held,), images_per_camera=0, lpips=False,
                                           progress=False))
    eval_db = [float(r["psnr"]) for r in sorted(ev.rows, key=lambda r: r["frame"])]
    view = {f: desktop(ckpt, camera, f, tmp / f"view_{f}.png") for f in frames}
    points = []
    with chromium() as browser:
        def point(route: str, variant: str, web: Path, **extra) -> None:
            per, against_view, seek_s, times = _browser_psnr(browser, web, camera, frames, truth, view, psnr)
            # a frame's time: the seeks that decoded or drew a new frame (the first frame is drawn at load)
            later = lambda xs: xs[1:] if len(xs) > 1 else xs  # noqa: E731
            frame_times = {"seek_per_frame_s": times["seek_s"], "frame_s_median": float(np.median(later(times["seek_s"])))}
            if times["decode_ms"]:
                frame_times.update(decode_ms=times["decode_ms"], prepare_ms=times["prepare_ms"],
                                   decode_ms_median=float(np.median(later(times["decode_ms"]))),
                                   prepare_ms_median=float(np.median(later(times["prepare_ms"]))))
            points.append({"route": route, "variant": variant, "bytes_per_frame": _stream_bytes(web) / n,
                           "psnr_db": float(np.mean(per)), "per_frame_db": per,
                           "view_db_min": float(min(against_view)), "view_per_frame_db": against_view,
                           "view_db_mean": float(np.mean(against_view)),
                           "delta_to_eval_db": float(np.mean(per)) - float(np.mean(eval_db)), "seek_s": seek_s,
                           **frame_times, "psnr_from": "the browser's pixels", **extra})
            print(points[-1]["variant"], f"{points[-1]['bytes_per_frame'] / 1e3:.0f} kB/frame",
                  f"{points[-1]['psnr_db']:.2f} dB", flush=True)

        for p in MODEL_PRECISIONS if "a" in routes else ():
            web = tmp / f"model-{p}"
            export(ckpt, web, ["--web-stream", "model", "--web-precision", p])
            point("a", f"model, {p}", web, precision=p)
        if "b" not in routes:
            return _curve(ckpt, data_dir, held, frames, n, eval_db, points)
        base = tmp / "gaussians"
        export(ckpt, base, ["--web-stream", "gaussians", "--chunk-frames", "8"])
        point("b", "Gaussians, as exported (8-frame chunks)", base)
        for cut in OPACITY_CUTS:
            web = tmp / f"gaussians-cut{cut}"
            _rewrite_chunks(base, web, opacity_cut=cut)
            point("b", f"Gaussians, opacity below {cut} dropped", web, opacity_cut=cut)
        for pos_bits, col_bits in COARSE:
            web = tmp / f"gaussians-coarse{pos_bits}-{col_bits}"
            _rewrite_chunks(base, web, coarse=(pos_bits, col_bits))
            point("b", f"Gaussians, {16 - pos_bits}-bit positions, {8 - col_bits}-bit colours", web,
                  coarse=[pos_bits, col_bits])
    return _curve(ckpt, data_dir, held, frames, n, eval_db, points)


def _curve(ckpt: Path, data_dir: Path, held: str, frames: list[int], n: int, eval_db: list[float],
           points: list[dict]) -> dict:
    return {"checkpoint": str(ckpt), "scene": str(data_dir), "camera": held, "frames": frames,
            "num_frames": n, "eval_psnr_db": float(np.mean(eval_db)), "eval_per_frame_db": eval_db, "points": points}


def bytes_table(r: dict, stamp: str) -> str:
    rows = [f"Measured {stamp} with `python bench/web.py --part bytes --checkpoint {r['checkpoint']}`: held-out "
            f"camera {r['camera']}, frames {', '.join(map(str, r['frames']))} of {r['num_frames']}; atgs-eval on the "
            f"same views: {r['eval_psnr_db']:.2f} dB. Every PSNR below is the browser's canvas (Chromium, software "
            "WebGL2) against the ground truth.", "",
            "| route | stream | bytes a frame | held-out PSNR | against atgs-eval | page against atgs-view (min) "
            "| seconds a seek (SwiftShader) |", "|---|---|---|---|---|---|---|"]
    for p in r["points"]:
        rows.append(f"| ({p['route']}) | {p['variant']} | {p['bytes_per_frame'] / 1e3:,.0f} kB | {p['psnr_db']:.2f} dB "
                    f"| {p['delta_to_eval_db']:+.2f} dB | {p['view_db_min']:.1f} dB | {p['seek_s']:.1f} |")
    return "\n".join(rows)


BYTES_TARGET = 0.15e6  # issue 50: at most 0.15 MB a frame ...
EVAL_DELTA_TARGET_DB = 0.3  # ... with the held-out PSNR from the browser's pixels within 0.3 dB of atgs-eval


def bytes_rows(r: dict | None) -> list[str]:
    """The README's rows of the model stream's points (none before --part bytes ran)."""
    if not r:
        return []
    ok = lambda good: "reached" if good else "not reached"  # noqa: E731
    rows = []
    for p in r["points"]:
        if p["route"] != "a":
            continue
        default = " (the default)" if p["precision"] == "int8" else ""
        rows.append(
            f"| the model stream (`--web-stream model`), {p['precision']}{default}, held-out camera {r['camera']} "
            f"({r['date']} at {r['commit']}) | {p['bytes_per_frame'] / 1e3:,.0f} kB a frame; held-out PSNR from the "
            f"browser's pixels {p['psnr_db']:.2f} dB, atgs-eval {r['eval_psnr_db']:.2f} dB; page against atgs-view "
            f"{p['view_db_min']:.1f} dB; {p['seek_s']:.1f} s a seek (decoded in SwiftShader) | 0.15 MB a frame: "
            f"{ok(p['bytes_per_frame'] <= BYTES_TARGET)}; within 0.3 dB of atgs-eval: "
            f"{ok(abs(p['delta_to_eval_db']) <= EVAL_DELTA_TARGET_DB)} |")
    return rows
