"""The web player: size of ``atgs-export --format web`` against the PLY export, and the page in
headless Chromium (software WebGL2 on this machine's CPUs: a floor, not a GPU figure) against
``atgs-view --headless`` of the same checkpoint, camera and frame.

    python bench/web.py --checkpoint runs/demo/ckpt.pt [--extra-checkpoint runs/n3dv/ckpt.pt]
    # writes bench/results/web.json and the table in README.md
    python bench/web.py --part bytes --checkpoint runs/demo/ckpt.pt [--scene PREPARED]
    # bytes a frame against held-out PSNR of both streams (bench/_web_bytes.py): the "bytes" key of
    # bench/results/web.json (the others kept) and the table in docs/web.md

Targets (issue 39): the web export at most 1/8 of the PLY export's bytes; the browser's frames at
least 35 dB against atgs-render; the first frame within 2 s of opening the page on localhost.
"""

from __future__ import annotations

import json
import os
import statistics
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import tyro

from _docs import publish, run_stamp, update_docs_table, write_json_atomic  # bench/_docs.py (the script's folder is on sys.path)
from _web_bytes import bytes_curve, bytes_table
from atgs.eval.metrics import psnr
from atgs.web.browser import PlayerPage, chromium, serving

SIZE_TARGET = 1 / 8
PSNR_TARGET_DB = 35.0
FIRST_FRAME_TARGET_S = 2.0


@dataclass
class BenchConfig:
    part: Literal["all", "bytes"] = "all"
    """all: size, browser against atgs-view, first frame, playback; bytes: the bytes-a-frame against
    held-out PSNR curve of both web streams (merged into --out under "bytes", table in docs/web.md)."""
    checkpoint: Path = Path("runs/demo/ckpt.pt")
    """The built-in scene's trained checkpoint (./scripts/demo.sh writes runs/demo/ckpt.pt)."""
    extra_checkpoints: list[Path] = field(default_factory=list)
    """More checkpoints whose web export size is reported (e.g. the real N3DV frame's model)."""
    extra_names: list[str] = field(default_factory=list)
    """What each of --extra-checkpoints is, for the table (default: its path)."""
    chunk_frames: int = 8
    views: int = 4
    """Frames (evenly spaced) compared on each of the held-out camera and one training camera."""
    loads: int = 3
    """Page loads timed to the first frame."""
    play_seconds: float = 8.0
    """Playback measured after the stream has loaded."""
    screenshot: Path | None = Path("docs/images/web_player.png")
    """The page at 1280x720 while playing (the README's picture); None: none."""
    replot: bool = False
    """Only rewrite the table from --out's results (no measurement)."""
    scene: Path | None = None
    """--part bytes: the prepared scene of the held-out ground truth (default: the checkpoint's data_dir)."""
    bytes_frames: int = 6
    """--part bytes: frames (evenly spaced) of the held-out camera."""
    bytes_docs: Path | None = Path("docs/web.md")
    """--part bytes: the page with the bench:web-bytes markers."""
    out: Path = Path("bench/results/web.json")
    docs: Path | None = Path("README.md")
    """The page with the bench:web markers (issue 39 asks for the figures in the README)."""


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(psnr(torch.from_numpy(a).double(), torch.from_numpy(b).double()))


def _bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def _desktop(ckpt: Path, camera: int, frame: int, out: Path) -> np.ndarray:
    from atgs.io.images import read_rgb8
    from atgs.viewer.cli import main as view_main

    assert view_main([str(ckpt), "--headless", "--device", "cpu", "--camera", str(camera), "--frame", str(frame),
                      "--out", str(out)]) == 0
    return read_rgb8(out).astype(np.float32) / 255.0


def _export(ckpt: Path, out: Path, fmt: str, chunk_frames: int, extra: list[str] | None = None) -> float:
    from atgs.cli.export import main as export_main

    t0 = time.perf_counter()
    args = [str(ckpt), "--out", str(out), "--format", fmt, "--no-progress", *(extra or [])]
    if fmt == "web" and extra is None:
        args += ["--web-stream", "gaussians", "--chunk-frames", str(chunk_frames)]
    assert export_main(args) == 0
    return time.perf_counter() - t0


def _drawn_per_frame(stream: Path, man: dict) -> list[int]:
    """Gaussians present in each exported frame (opacity above 0 as stored; the reference reader)."""
    from atgs.web.stream_format import decode_chunk

    return [int((fr.opacities > 0).sum()) for c in man["chunks"]
            for fr in decode_chunk((stream / c["file"]).read_bytes()).frames]


def size_row(ckpt: Path, tmp: Path, chunk_frames: int, with_ply: bool) -> tuple[dict, Path]:
    """The web export's (and with ``with_ply`` the PLY export's) size; (row, the web folder)."""
    web = tmp / f"web-{len(list(tmp.glob('web-*')))}"
    web_s = _export(ckpt, web, "web", chunk_frames)
    man = json.loads((web / "stream" / "manifest.json").read_text())
    stream = sum(c["bytes"] for c in man["chunks"])
    frames = len(man["frames"])
    union = sum(c["gaussians"] * c["frames"] for c in man["chunks"])
    static = sum(c["static"] * c["frames"] for c in man["chunks"])
    drawn = _drawn_per_frame(web / "stream", man)
    row = {"checkpoint": str(ckpt), "step": man["source"].get("step"), "frames": frames,
           "chunks": len(man["chunks"]), "chunk_frames": chunk_frames,
           "export_s": web_s, "stream_bytes": stream, "folder_bytes": _bytes(web),
           "bytes_per_frame": stream / frames, "bytes_per_gaussian_frame": stream / sum(drawn),
           "gaussians_per_frame_mean": sum(drawn) / frames, "static_share": static / union}
    if with_ply:
        ply = tmp / f"ply-{web.name}"
        row["ply_export_s"] = _export(ckpt, ply, "ply", chunk_frames)
        row["ply_bytes"] = _bytes(ply)
        row["ratio_to_ply"] = row["folder_bytes"] / row["ply_bytes"]
    return row, web


def _views(man: dict, views: int) -> tuple[list[int], list[int], list[int]]:
    """(the first held-out camera and the first training camera, the held-out ones, ``views``
    evenly spaced exported frames)."""
    n = len(man["frames"])
    held = [i for i, c in enumerate(man["cameras"]) if c.get("held_out")]
    cams = (held[:1] or [0]) + [next(i for i, c in enumerate(man["cameras"]) if not c.get("held_out"))]
    return cams, held, sorted({round(k * (n - 1) / max(views - 1, 1)) for k in range(views)})


def compare_views(browser, url: str, ckpt: Path, man: dict, views: int, tmp: Path) -> list[dict]:
    """PSNR of the page's canvas against atgs-view --headless, per camera and frame."""
    cams, held, frames = _views(man, views)
    rows = []
    for cam in cams:
        page = PlayerPage(browser, url, {"camera": cam, "paused": 1, "size": "camera"})
        page.first_frame()
        for i in frames:
            page.seek(i)
            got = page.pixels()
            want = _desktop(ckpt, cam, man["frames"][i], tmp / f"d{cam}_{i}.png")
            rows.append({"camera": man["cameras"][cam]["name"], "held_out": cam in held,
                         "frame": man["frames"][i], "size": list(got.shape[1::-1]), "db": _psnr(got, want)})
        page.close()
    return rows


def browser_rows(ckpt: Path, web: Path, cfg: BenchConfig, tmp: Path) -> dict:
    man = json.loads((web / "stream" / "manifest.json").read_text())
    cams, _, _ = _views(man, cfg.views)
    out: dict = {"psnr": [], "first_frame_s": []}
    with chromium() as browser, serving(web) as url:
        out["psnr"] = compare_views(browser, url, ckpt, man, cfg.views, tmp)
        for _ in range(cfg.loads):
            page = PlayerPage(browser, url, {"camera": cams[0], "paused": 1, "size": "camera"})
            page.first_frame()
            out["first_frame_s"].append(page.state()["firstFrameMs"] / 1000)
            page.close()
        for size in ("camera", None):
            params = {"camera": cams[0]} | ({"size": size} if size else {})
            page = PlayerPage(browser, url, params)
            if size is None:
                page.page.set_viewport_size({"width": 1280, "height": 720})
            page.first_frame()
            page.page.wait_for_function("() => { const s = window.atgsPlayer.state(); "
                                        "return s.loadedBytes >= s.totalBytes; }", timeout=120_000)
            s0, t0 = page.state(), time.perf_counter()
            time.sleep(cfg.play_seconds)
            s1, t1 = page.state(), time.perf_counter()
            w, h = page.page.evaluate("() => { const c = document.querySelector('canvas'); "
                                      "return [c.width, c.height]; }")
            if size is None and cfg.screenshot is not None:
                page.page.screenshot(path=str(cfg.screenshot))
            out.setdefault("playback", []).append({
                "canvas": [w, h], "draws_per_s": (s1["framesDrawn"] - s0["framesDrawn"]) / (t1 - t0),
                "page_draw_fps": s1.get("drawFps"), "video_fps": man["fps"]})
            page.close()
    return out


def run(cfg: BenchConfig) -> dict:
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        main_row, web = size_row(cfg.checkpoint, tmp, cfg.chunk_frames, with_ply=True)
        pages = browser_rows(cfg.checkpoint, web, cfg, tmp)
        extra = []
        for i, ckpt in enumerate(cfg.extra_checkpoints):
            row, web = size_row(ckpt, tmp, cfg.chunk_frames, with_ply=False)
            row["name"] = cfg.extra_names[i] if i < len(cfg.extra_names) else str(ckpt)
            man = json.loads((web / "stream" / "manifest.json").read_text())
            with chromium() as browser, serving(web) as url:
                row["psnr"] = compare_views(browser, url, ckpt, man, 2, tmp)
            extra.append(row)
    psnrs = [p["db"] for p in pages["psnr"]]
    return {"size": main_row, "extra": extra, "browser": pages,
            "summary": {"ratio_to_ply": main_row["ratio_to_ply"], "psnr_min_db": min(psnrs),
                        "psnr_median_db": statistics.median(psnrs),
                        "first_frame_s_median": statistics.median(pages["first_frame_s"])},
            "machine": {"cpus": os.cpu_count(), "loadavg_before": list(load_before)}, **run_stamp()}


def markdown_table(r: dict) -> str:
    s, b, m = r["size"], r["browser"], r["summary"]
    ok = lambda good: "reached" if good else "not reached"  # noqa: E731
    rows = [
        f"Measured {r['date']} at {r['commit']} with `python bench/web.py --checkpoint {s['checkpoint']}` on "
        f"{r['machine']['cpus']} CPUs; Chromium with software WebGL2 (SwiftShader): browser figures are a floor.", "",
        "| what | measured | target |", "|---|---|---|",
        f"| web export of the built-in scene's model ({s['step']:,} steps) | {s['folder_bytes'] / 2**20:.1f} MiB "
        f"for {s['frames']} frames: "
        f"{s['bytes_per_frame'] / 1024:.0f} KiB a frame, {s['bytes_per_gaussian_frame']:.2f} B per Gaussian a frame "
        f"({s['gaussians_per_frame_mean']:,.0f} Gaussians a frame; {100 * s['static_share']:.0f}% of each chunk's "
        f"Gaussians unchanged over it, stored once) | |",
        f"| PLY export of the same frames | {s['ply_bytes'] / 2**20:.1f} MiB | |",
        f"| web / PLY bytes | 1/{1 / s['ratio_to_ply']:.1f} | at most 1/8: {ok(s['ratio_to_ply'] <= SIZE_TARGET)} |",
        f"| browser against atgs-view --headless, {len(b['psnr'])} views | min {m['psnr_min_db']:.1f} dB, "
        f"median {m['psnr_median_db']:.1f} dB | 35 dB: {ok(m['psnr_min_db'] >= PSNR_TARGET_DB)} |",
        f"| first frame after opening the page (localhost, {len(b['first_frame_s'])} loads) | median "
        f"{m['first_frame_s_median']:.2f} s (max {max(b['first_frame_s']):.2f} s) | 2 s: "
        f"{ok(max(b['first_frame_s']) <= FIRST_FRAME_TARGET_S)} |",
    ]
    for p in b["playback"]:
        rows.append(f"| playback, canvas {p['canvas'][0]}x{p['canvas'][1]} | {p['draws_per_s']:.1f} frames drawn a "
                    f"second (video at {p['video_fps']:g} fps) | a floor |")
    for e in r["extra"]:
        db = [p["db"] for p in e["psnr"]]
        rows.append(f"| web export of {e['name']} ({e['step']:,} steps) | "
                    f"{e['bytes_per_gaussian_frame']:.2f} B per Gaussian a frame, {e['gaussians_per_frame_mean']:,.0f} "
                    f"Gaussians, {e['frames']} frame(s); browser against atgs-view {min(db):.1f}-{max(db):.1f} dB "
                    f"({len(db)} views at {e['psnr'][0]['size'][0]}x{e['psnr'][0]['size'][1]}) | |")
    return "\n".join(rows)


def run_bytes(cfg: BenchConfig) -> None:
    """--part bytes: the curve, merged into --out (its other keys kept) and tabled in docs/web.md."""
    with tempfile.TemporaryDirectory() as d:
        curve = bytes_curve(cfg.checkpoint, cfg.scene, cfg.bytes_frames, Path(d),
                            lambda ckpt, out, extra: _export(ckpt, out, "web", cfg.chunk_frames, extra), _desktop,
                            _psnr)
    curve.update(machine={"cpus": os.cpu_count()}, **run_stamp())
    result = json.loads(cfg.out.read_text()) if cfg.out.exists() else {}
    result["bytes"] = curve
    write_json_atomic(cfg.out, result)
    table = bytes_table(curve, f"{curve['date']} at {curve['commit']}")
    print(table)
    if cfg.bytes_docs is not None:
        update_docs_table(cfg.bytes_docs, "web-bytes", table)


def main(cfg: BenchConfig) -> None:
    if cfg.part == "bytes":
        run_bytes(cfg)
        return
    if cfg.replot:
        result = json.loads(cfg.out.read_text())
        publish(result, cfg.out, markdown_table(result), cfg.docs, "web")
        return
    for c in [cfg.checkpoint, *cfg.extra_checkpoints]:
        if not c.is_file():
            raise SystemExit(f"bench/web.py: {c} does not exist; train one with atgs-train and pass its ckpt.pt")
    result = run(cfg)
    publish(result, cfg.out, markdown_table(result), cfg.docs, "web")


if __name__ == "__main__":
    main(tyro.cli(BenchConfig))
