"""GPU benchmark (issue 13): what a GPU buys end to end, with the device name on every row.

    python bench/gpu.py                    # writes bench/results/gpu.json and the table in docs/gpu.md
    python bench/gpu.py --parts train      # one part; the results of the others are kept
    python bench/gpu.py --merge FILE       # take the rows of a results file from another machine

Rows, one function each (``PARTS``; each returns a list of row dicts with a ``device``):
- train: training steps per second of each preset on an N3DV-like scene (bench/_n3dv_like.py:
  20 cameras, 1352x1014 on CUDA; the CPU rows at a quarter of that size, labelled), through
  ``atgs.train.trainer.Trainer(device=...)`` as ``atgs-train --device`` runs it;
- viewer: FPS of the splatting player at 1920x1080 for 100k / 500k / 1M random Gaussians, for a
  new video frame (pack + upload + sort + draw, the Gaussians starting on the device) and for a
  camera move (sort + draw), with the stages' times;
- decode: ms per frame of an untrained ATGS model of the ``paper`` and ``cpu`` presets
  (``model.gaussians_at_frame`` + packing, i.e. what the player's decode thread does);
- content: the player on trained checkpoints (``--checkpoints``), seen from their first held-out
  camera at 1920x1080: a new video frame (decode + pack, upload, sort, draw) and a camera move,
  with what sets the draw's cost: the Gaussians drawn, the fragments each one writes and the
  overdraw (fragments per pixel), counted by the GL (a samples-passed query), and the draw time
  with each blend-target precision (8-bit, half and float RGBA).
- content_gl: the same with ``--decode gl``: the frame decoded by a compute shader into GL
  buffers, sorted on the GL and drawn indirectly (nothing through host memory), with GL time
  queries of the decode dispatch, a whole new frame and a camera move.
Each part runs on CUDA when torch sees a CUDA device (training: and gsplat imports) and on the
CPU; a CUDA row without them is written as ``"not measured"`` with the reason. The OpenGL draw
runs wherever the headless context lives (its renderer string is in the part's ``machine.gl``:
llvmpipe is the CPU).
"""

from __future__ import annotations


from _docs import publish  # bench/ (the script's own folder is on sys.path)
from _viewer_scenes import bench_camera, random_gaussians, time_frames, untrained_model, warm_renderer

import json
import os
import platform
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import torch
import tyro

from atgs.headless_gl import gl_description
from atgs.io.atomic import write_json_atomic
from atgs.progress import progress_bar
from atgs.viewer.source import decode_frame
from atgs.viewer.splat_renderer import SplatRenderer

NOT_MEASURED = "not measured"


@dataclass
class GpuBenchConfig:
    counts: tuple[int, ...] = (100_000, 500_000, 1_000_000)
    size: tuple[int, int] = (1920, 1080)
    repeats: int = 2
    """New frames (and camera moves) timed per count; the median is reported."""
    presets: tuple[str, ...] = ("paper", "cpu")
    decode_points: int = 6_000
    """Points of the synthetic scene the untrained models are initialised from (as bench/viewer.py)."""
    decode_frames: int = 6
    """Frames decoded per model after the first (which builds the decode caches)."""
    devices: tuple[str, ...] = ("cuda", "cpu")
    parts: tuple[str, ...] = ("train", "viewer", "decode")
    train_presets: tuple[str, ...] = ("cpu-fast", "cpu", "cpu-accurate", "paper")
    train_size: tuple[int, int] = (1352, 1014)
    """Image size of the CUDA training rows (N3DV at half resolution, as trained in the paper)."""
    cpu_train_size: tuple[int, int] = (338, 254)
    """Image size of the CPU training rows (a quarter of N3DV's: a CPU step at full size takes minutes)."""
    train_cameras: int = 20
    train_frames: int = 6
    train_points: int = 10_000
    """Points per keyframe (3 keyframes) the anchors are initialised from."""
    train_warmup: int = 5
    """Steps before timing (gsplat's kernels, allocator caches)."""
    train_steps: int = 50
    """Timed steps per preset on CUDA."""
    cpu_train_steps: int = 10
    """Timed steps per preset on the CPU."""
    gl: str = "auto"
    out: Path = Path("bench/results/gpu.json")
    docs: Path | None = Path("docs/gpu.md")
    """Replace the table between the bench:gpu markers in this file (None: leave the docs alone)."""
    checkpoints: tuple[Path, ...] = ()
    """Trained checkpoints of the ``content`` part (the optimizer state may be stripped: only
    the model is read)."""
    content_frames: int = 6
    """New video frames timed per checkpoint (spread over the video), after one untimed frame."""
    merge: Path | None = None
    """Measure nothing: take every part/device of this results file (written by this script on
    another machine, e.g. a GPU one with ``--docs None``) into ``out``, replacing those rows."""


def device_name(device: str) -> str:
    if device == "cuda":
        return torch.cuda.get_device_name(0)
    return f"CPU ({os.cpu_count()} cores, {platform.processor() or platform.machine()})"


def unavailable(device: str, part: str) -> str | None:
    """Why ``part`` cannot be measured on ``device`` here (None: it can): atgs-train's and
    atgs-view's rule (atgs.device), training needing gsplat as well."""
    from atgs.device import cuda_problem

    if device != "cuda" or cuda_problem(need_gsplat=part == "train") is None:
        return None
    if not torch.cuda.is_available():
        return f"{NOT_MEASURED} (no CUDA device: torch {torch.__version__} sees none)"
    return f"{NOT_MEASURED} ({cuda_problem(need_gsplat=True).split(';')[0]})"


def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


@lru_cache(maxsize=2)
def _n3dv_scene(size: tuple[int, int], cameras: int, frames: int, points: int):
    from _n3dv_like import n3dv_like_scene

    return n3dv_like_scene(size, cameras=cameras, frames=frames, points_per_keyframe=points)


def train_rows(cfg: GpuBenchConfig, device: str, renderer: SplatRenderer) -> list[dict]:
    """Training steps/s of each preset on the N3DV-like scene: every image in the trainer's
    cache first (on the device), ``train_warmup`` steps, then the timed steps. The steps are
    the first of a run: the initial anchors, before densification (it starts at step >= 100)."""
    from _harness import build_trainer, timed_steps
    from atgs.train.config import preset

    size = cfg.train_size if device == "cuda" else cfg.cpu_train_size
    steps = cfg.train_steps if device == "cuda" else cfg.cpu_train_steps
    scene = _n3dv_scene(tuple(size), cfg.train_cameras, cfg.train_frames, cfg.train_points)
    images_mb = sum(a.nbytes for a in scene.frames.values()) / 2**20
    rows = []
    for name in cfg.train_presets:
        cache_mb = max(preset(name)[1].image_cache_mb, int(images_mb) + 1)  # every image cached
        with tempfile.TemporaryDirectory() as out:
            t0 = time.perf_counter()
            tr = build_trainer(scene, Path(out) / "run", name, train={"image_cache_mb": cache_mb}, threads=0,
                               device=device)
            for ci in tr.train_idx:
                for f in range(scene.num_frames):
                    tr.images.get(ci, f)
            init_s = time.perf_counter() - t0
            anchors = tr.model.num_anchors
            for _ in range(cfg.train_warmup):
                tr.train_step()
            if device == "cuda":
                torch.cuda.reset_peak_memory_stats()
            results, seconds = timed_steps(tr, steps)
        row = {"part": "train", "device": device, "device_name": device_name(device), "preset": name,
               "size": f"{size[0]}x{size[1]}", "cameras": len(scene.cameras), "frames": scene.num_frames,
               "anchors": anchors, "gaussians_per_view": int(statistics.mean(r.gaussians for r in results)),
               "skipped": sum(r.skipped for r in results), "init_s": init_s, "steps": steps,
               "ms_per_step": 1e3 * seconds / steps, "steps_per_s": steps / seconds,
               "peak_gpu_mb": torch.cuda.max_memory_allocated() / 2**20 if device == "cuda" else None,
               "torch_threads": torch.get_num_threads(), "loadavg": os.getloadavg()}
        rows.append(row)
        print(json.dumps(row))
        del tr
    return rows


def _median(xs: list[float]) -> float:
    return float(statistics.median(xs))


def viewer_rows(cfg: GpuBenchConfig, device: str, renderer: SplatRenderer) -> list[dict]:
    """Player FPS at cfg.size for each count: a new frame (the Gaussians on the device are packed
    there, copied to host memory, uploaded, sorted on the device and drawn) and a camera move."""
    W, H = cfg.size
    rows = []
    renderer.target_dtype = "f1"  # the window's RGBA8 target
    for n in cfg.counts:
        row = {"part": "viewer", "device": device, "device_name": device_name(device), "gaussians": n,
               "size": f"{W}x{H}", **time_frames(renderer, random_gaussians(n, device=device), W, H, cfg.repeats),
               "loadavg": os.getloadavg()}
        renderer._sort_key = type(renderer._sort_key)()  # force a sort: the counts are of this camera
        drawn, fragments, _ = draw_counts(renderer, bench_camera(W, H))
        row.update(drawn=drawn, fragments_per_splat=fragments / max(drawn, 1), overdraw=fragments / (W * H))
        rows.append(row)
        print(json.dumps(row))
    return rows


def decode_rows(cfg: GpuBenchConfig, device: str, renderer: SplatRenderer) -> list[dict]:
    """ms per decoded + packed frame of an untrained model of each preset, on ``device``: the
    model moves there (``ATGSModel.to``, through the player's ``place_source``) and decodes and
    packs there."""
    from atgs.viewer.device import place_source

    rows = []
    for preset_name in cfg.presets:
        model = untrained_model(preset_name, cfg.decode_points)
        source = place_source(model, torch.device(device))
        where = str(source.device)  # ATGSModel.to moves the model in place
        first = decode_frame(source, 0, device)
        frames = [1 + i % (model.num_frames - 1) for i in range(cfg.decode_frames)]
        ms = [decode_frame(source, f, device).decode_ms for f in frames]
        row = {"part": "decode", "device": device, "device_name": device_name(device), "preset": preset_name,
               "decoded_on": where, "anchors": model.num_anchors, "gaussians": len(first),
               "first_frame_ms": first.decode_ms, "decode_ms": _median(ms), "frames": len(ms),
               "loadavg": os.getloadavg()}
        rows.append(row)
        print(json.dumps(row))
    return rows


def content_camera(ckpt_camera, size: tuple[int, int], yaw_deg: float = 0.0):
    """``ckpt_camera`` at ``size``: the same vertical field of view and centre (a wider image
    shows more to the sides), turned by ``yaw_deg`` about its own vertical axis."""
    import math

    import numpy as np

    from atgs.cameras import Camera

    W, H = size
    s = H / ckpt_camera.height
    K = ckpt_camera.K.copy()
    K[:2, :2] *= s
    K[0, 2] = W / 2 + (ckpt_camera.cx - ckpt_camera.width / 2) * s
    K[1, 2] = H / 2 + (ckpt_camera.cy - ckpt_camera.height / 2) * s
    a = math.radians(yaw_deg)
    turn = np.eye(4)
    turn[[0, 0, 2, 2], [0, 2, 0, 2]] = [math.cos(a), math.sin(a), -math.sin(a), math.cos(a)]
    return Camera(f"{ckpt_camera.name}@{W}x{H}", W, H, K, turn @ ckpt_camera.w2c)


def draw_counts(renderer: SplatRenderer, camera) -> tuple[int, int, float]:
    """(Gaussians drawn, fragments written, GPU draw ms) of one draw, read from GL queries: the
    fragments are those that pass the fragment shader (its alpha and 3-sigma cuts discard the
    rest), so fragments / pixels is the overdraw the blend pays for."""
    query = renderer.ctx.query(samples=True, time=True)
    with query:
        renderer.render(camera, sync=True)
    return renderer.timings.drawn, int(query.samples), query.elapsed / 1e6


def content_rows(cfg: GpuBenchConfig, device: str, renderer: SplatRenderer) -> list[dict]:
    """The player on each trained checkpoint: decode + pack on ``device`` (the model moved
    there), upload, sort and draw at cfg.size from the first held-out camera (or the first
    camera), for ``content_frames`` frames spread over the video; a camera move (a 1 degree
    turn) re-sorts and draws the same frame."""
    import atgs
    from atgs.viewer.device import place_source

    W, H = cfg.size
    rows = []
    for path in cfg.checkpoints:
        model = atgs.load(path, device="cpu")
        source = place_source(model, torch.device(device))
        by_name = {c.name: c for c in model.cameras}
        held = [by_name[n] for n in getattr(model, "test_camera_names", []) if n in by_name]
        base = (held or model.cameras)[0]
        cam = content_camera(base, (W, H))
        frames = [round(i * (model.num_frames - 1) / max(cfg.content_frames - 1, 1)) for i in range(cfg.content_frames)]
        renderer.target_dtype = "f1"  # the window's RGBA8 target
        renderer.set_gaussians(decode_frame(source, frames[-1], device))  # untimed: caches, first-use costs
        renderer.render(content_camera(base, (W, H), 0.5), sync=True)
        t = {k: [] for k in ("decode_pack_ms", "upload_ms", "sort_ms", "draw_ms", "move_sort_ms", "move_draw_ms")}
        drawn, frags, gpu_draw = [], [], []
        for f in frames:
            _sync(device)
            packed = decode_frame(source, f, device)
            t["decode_pack_ms"].append(packed.decode_ms)
            t["upload_ms"].append(renderer.set_gaussians(packed))
            renderer.render(cam, sync=True)
            t["sort_ms"].append(renderer.timings.sort_ms)
            t["draw_ms"].append(renderer.timings.draw_ms)
            renderer.render(content_camera(base, (W, H), 1.0), sync=True)
            t["move_sort_ms"].append(renderer.timings.sort_ms)
            t["move_draw_ms"].append(renderer.timings.draw_ms)
            renderer._sort_key = type(renderer._sort_key)()  # force the sort: the counts below are of ``cam``
            n, k, g_ms = draw_counts(renderer, cam)
            drawn.append(n), frags.append(k), gpu_draw.append(g_ms)
        precision, precision_gpu = {}, {}
        for dtype in ("f1", "f2", "f4"):
            renderer.target_dtype = dtype
            renderer.render(cam, sync=True)  # target made, sorted
            wall = []
            for _ in range(3):
                renderer.render(cam, sync=True)
                wall.append(renderer.timings.draw_ms)
            precision[dtype] = _median(wall)
            precision_gpu[dtype] = _median([draw_counts(renderer, cam)[2] for _ in range(3)])
        renderer.target_dtype = "f1"
        m = {k: _median(v) for k, v in t.items()}
        new_frame = m["decode_pack_ms"] + m["upload_ms"] + m["sort_ms"] + m["draw_ms"]
        move = m["move_sort_ms"] + m["move_draw_ms"]
        row = {"part": "content", "device": device, "device_name": device_name(device),
               "checkpoint": f"{path.parent.name or path}, {W}x{H}", "camera": base.name, "size": f"{W}x{H}",
               "frames": len(frames), "anchors": model.num_anchors,
               "gaussians": int(_median([len(decode_frame(source, frames[0], device))])),
               "drawn": int(_median(drawn)), "fragments": int(_median(frags)),
               "fragments_per_splat": _median([k / max(n, 1) for n, k in zip(drawn, frags)]),
               "overdraw": _median(frags) / (W * H), "gpu_draw_ms": _median(gpu_draw),
               "draw_ms_by_target": precision, "gpu_draw_ms_by_target": precision_gpu, **m,
               "fps_new_frame": 1000.0 / new_frame, "fps_camera_move": 1000.0 / move,
               "loadavg": os.getloadavg()}
        rows.append(row)
        print(json.dumps(row))
    return rows


def content_gl_rows(cfg: GpuBenchConfig, device: str, renderer: SplatRenderer) -> list[dict]:
    """The player on each trained checkpoint with ``--decode gl``: the frame decoded by the
    compute shader into GL buffers, sorted on the GL and drawn indirectly (viewer.gl_decode,
    viewer.gl_sort), nothing through host memory; the same camera and frames as ``content``.
    GPU times come from GL time queries: the decode dispatch alone, and a whole new frame."""
    import atgs
    from atgs.viewer.gl_decode import GLFrameDecoder

    W, H = cfg.size
    rows = []
    for path in cfg.checkpoints:
        model = atgs.load(path, device="cpu")
        by_name = {c.name: c for c in model.cameras}
        held = [by_name[n] for n in getattr(model, "test_camera_names", []) if n in by_name]
        base = (held or model.cameras)[0]
        cam, moved = content_camera(base, (W, H)), content_camera(base, (W, H), 1.0)
        frames = [round(i * (model.num_frames - 1) / max(cfg.content_frames - 1, 1)) for i in range(cfg.content_frames)]
        decoder = GLFrameDecoder(renderer.ctx, model)
        renderer.target_dtype = "f1"  # the window's RGBA8 target
        renderer.set_gl_frame(decoder.decode(frames[-1]))  # untimed: compiles, buffers, first use
        renderer.render(content_camera(base, (W, H), 0.5), sync=True)
        t = {k: [] for k in ("decode_issue_ms", "decode_gpu_ms", "new_frame_ms", "new_frame_gpu_ms",
                             "move_ms", "move_gpu_ms")}
        drawn = []
        for f in frames:
            renderer.ctx.finish()
            query = renderer.ctx.query(time=True)
            t0 = time.perf_counter()
            with query:
                frame = decoder.decode(f)
            renderer.ctx.finish()
            t["decode_issue_ms"].append(frame.decode_ms)
            t["decode_gpu_ms"].append(query.elapsed / 1e6)
            # a whole new frame: decode, sort and draw, waited for
            query = renderer.ctx.query(time=True)
            t0 = time.perf_counter()
            with query:
                renderer.set_gl_frame(decoder.decode(f))
                renderer.render(cam, sync=False)
            renderer.ctx.finish()
            t["new_frame_ms"].append((time.perf_counter() - t0) * 1e3)
            t["new_frame_gpu_ms"].append(query.elapsed / 1e6)
            drawn.append(renderer.drawn_count())
            query = renderer.ctx.query(time=True)
            t0 = time.perf_counter()
            with query:
                renderer.render(moved, sync=False)
            renderer.ctx.finish()
            t["move_ms"].append((time.perf_counter() - t0) * 1e3)
            t["move_gpu_ms"].append(query.elapsed / 1e6)
        decoder.release()
        m = {k: _median(v) for k, v in t.items()}
        row = {"part": "content_gl", "device": device, "device_name": device_name(device),
               "gl": renderer.ctx.info.get("GL_RENDERER", "?"),
               "checkpoint": f"{path.parent.name or path}, {W}x{H}", "camera": base.name, "size": f"{W}x{H}",
               "frames": len(frames), "anchors": model.num_anchors, "slots": frame.count,
               "drawn": int(_median(drawn)), **m,
               "fps_new_frame": 1000.0 / m["new_frame_ms"], "fps_camera_move": 1000.0 / m["move_ms"],
               "loadavg": os.getloadavg()}
        rows.append(row)
        print(json.dumps(row))
    return rows


# Each part: name -> function(cfg, device, renderer) -> rows.
PARTS: dict[str, Callable[[GpuBenchConfig, str, SplatRenderer], list[dict]]] = {
    "train": train_rows,
    "viewer": viewer_rows,
    "decode": decode_rows,
    "content": content_rows,
    "content_gl": content_gl_rows,
}


def part_table(rows: list[dict], head: list[str], key: str, cells: Callable[[dict], list[str]]) -> list[str]:
    """Markdown rows of one part: device, its name, ``key`` (what the row measures), then
    ``cells(row)``; a row with a ``status`` (not measured) gets that text instead."""
    if not rows:
        return []
    lines = ["", "| " + " | ".join(head) + " |", "|---|---|" + "---:|" * (len(head) - 2)]
    for r in rows:
        first = [r["device"], r["device_name"], f"{r[key]:,}" if isinstance(r[key], int) else str(r[key])]
        rest = [r["status"]] + [""] * (len(head) - 4) if "status" in r else cells(r)
        lines.append("| " + " | ".join(first + rest) + " |")
    return lines


def _stamp(stamp: dict, device: str) -> str:
    m = stamp["machine"]
    where = f"{m['cuda']}, " if device == "cuda" and m.get("cuda", NOT_MEASURED) != NOT_MEASURED else ""
    return (f"Measured {stamp['date']}: {where}{m['cpus']} CPUs, OpenGL {m['gl']}, torch {m['torch']}; "
            f"load average before: {', '.join(f'{x:.1f}' for x in m['loadavg_before'])}.")


def markdown_table(result: dict) -> str:
    """One table per part and device, each under the line saying when and where it was measured
    (a GPU session and a CPU session rarely happen on the same day)."""
    rows, lines = result["rows"], []
    tables = {
        "train": (["training, N3DV-like scene: device", "name", "preset", "image size", "anchors",
                   "Gaussians per view", "ms per step", "steps/s", "peak GPU MB"], "preset",
                  lambda r: [r["size"], f"{r['anchors']:,}", f"{r['gaussians_per_view']:,}",
                             f"{r['ms_per_step']:.0f}", f"**{r['steps_per_s']:.2f}**",
                             "" if r["peak_gpu_mb"] is None else f"{r['peak_gpu_mb']:,.0f}"]),
        "viewer": (["viewer at 1920x1080, random Gaussians: device", "name", "Gaussians", "drawn",
                    "mean splat area (px)", "overdraw", "pack ms", "upload ms", "sort ms", "draw ms",
                    "new frame FPS", "camera move FPS"], "gaussians",
                   lambda r: [f"{r['drawn']:,}" if "drawn" in r else "", f"{r['fragments_per_splat']:.0f}" if "drawn" in r else "",
                              f"{r['overdraw']:.1f}" if "drawn" in r else "",
                              f"{r['pack_ms']:.1f}", f"{r['upload_ms']:.1f}", f"{r['sort_ms']:.1f}",
                              f"{r['draw_ms']:.0f}", f"**{r['fps_new_frame']:.2f}**",
                              f"**{r['fps_camera_move']:.2f}**"]),
        "decode": (["decode + pack, untrained model: device", "name", "preset", "decoded on", "anchors", "Gaussians",
                    "first frame ms", "ms per frame"], "preset",
                   lambda r: [r["decoded_on"], f"{r['anchors']:,}", f"{r['gaussians']:,}",
                              f"{r['first_frame_ms']:.0f}", f"**{r['decode_ms']:.1f}**"]),
        "content": (["player on a trained checkpoint: device", "name", "checkpoint, size", "Gaussians drawn",
                     "mean splat area (px)", "overdraw", "decode + pack ms", "upload ms", "sort ms", "draw ms",
                     "draw ms, RGBA8 / half / float target", "new frame FPS", "camera move FPS"], "checkpoint",
                    lambda r: [f"{r['drawn']:,}", f"{r['fragments_per_splat']:.0f}", f"{r['overdraw']:.1f}",
                               f"{r['decode_pack_ms']:.1f}", f"{r['upload_ms']:.1f}", f"{r['sort_ms']:.1f}",
                               f"{r['draw_ms']:.1f}",
                               " / ".join(f"{r['draw_ms_by_target'][d]:.1f}" for d in ("f1", "f2", "f4")),
                               f"**{r['fps_new_frame']:.1f}**", f"**{r['fps_camera_move']:.1f}**"]),
        "content_gl": (["player, --decode gl (decode and sort on the GL): device", "name", "checkpoint, size", "GL",
                        "Gaussians drawn", "decode GPU ms", "new frame ms (GPU)", "camera move ms (GPU)",
                        "new frame FPS", "camera move FPS"], "checkpoint",
                       lambda r: [r["gl"].split(" (")[0], f"{r['drawn']:,}", f"{r['decode_gpu_ms']:.1f}",
                                  f"{r['new_frame_ms']:.1f} ({r['new_frame_gpu_ms']:.1f})",
                                  f"{r['move_ms']:.1f} ({r['move_gpu_ms']:.1f})",
                                  f"**{r['fps_new_frame']:.1f}**", f"**{r['fps_camera_move']:.1f}**"]),
    }
    for part, (head, key, cells) in tables.items():
        for device in ("cuda", "cpu"):
            group = [r for r in rows if r["part"] == part and r["device"] == device]
            if group:
                lines += ([""] if lines else []) + [_stamp(result["parts"][f"{part}/{device}"], device)]
                lines += part_table(group, head, key, cells)
    return "\n".join(lines)


def previous_stamps(path: Path) -> tuple[dict, list[dict]]:
    """("part/device" -> its date and machine, rows) of an earlier results file; empty if there
    is none. Files of the older layout (one stamp per part) give each of its devices that stamp."""
    if not path.exists():
        return {}, []
    old = json.loads(path.read_text())
    rows = old.get("rows", [])
    stamps = old.get("parts") or {r["part"]: {"date": old["date"], "machine": old["machine"]} for r in rows}
    out = {}
    for key, stamp in stamps.items():
        if "/" in key:
            out[key] = stamp
        else:
            out.update({f"{key}/{r['device']}": stamp for r in rows if r["part"] == key})
    return out, rows


def _result(stamps: dict, rows: list[dict]) -> dict:
    order = [f"{p}/{d}" for p in PARTS for d in ("cuda", "cpu")]
    return {"parts": dict(sorted(stamps.items(), key=lambda kv: order.index(kv[0]))),
            "rows": sorted(rows, key=lambda r: (list(PARTS).index(r["part"]), r["device"] != "cuda")),
            "date": max((s["date"] for s in stamps.values()), default="")}


def main(cfg: GpuBenchConfig) -> None:
    """Measures ``cfg.parts`` on ``cfg.devices``; the results file keeps the rows (and the
    measurement stamps) of every other part and device. It is written after each part on each
    device, so a later part that fails (or crashes the process) loses only its own rows."""
    stamps, rows = previous_stamps(cfg.out)
    if cfg.merge is not None:
        their_stamps, their_rows = previous_stamps(cfg.merge)
        taken = {tuple(key.split("/")) for key in their_stamps}
        rows = [r for r in rows if (r["part"], r["device"]) not in taken] + their_rows
        result = _result({**stamps, **their_stamps}, rows)
        publish(result, cfg.out, markdown_table(result), cfg.docs, "gpu")
        return
    load_before = os.getloadavg()
    ctx, renderer = warm_renderer(cfg.gl)
    # what an unmeasured part's rows would have covered (one "not measured" row each)
    row_keys = {"train": ("preset", cfg.train_presets), "viewer": ("gaussians", cfg.counts),
                "decode": ("preset", cfg.presets),
                "content": ("checkpoint", tuple(p.parent.name or str(p) for p in cfg.checkpoints)),
                "content_gl": ("checkpoint", tuple(p.parent.name or str(p) for p in cfg.checkpoints))}
    jobs = [(part, device) for part in cfg.parts for device in cfg.devices]
    with progress_bar(len(jobs), "gpu bench", unit="part") as bar:
        for part, device in jobs:
            reason = unavailable(device, part)
            if reason is None:
                new_rows = PARTS[part](cfg, device, renderer)
            else:
                key, values = row_keys[part]
                new_rows = [{"part": part, "device": device, "device_name": "none", key: v, "status": reason}
                            for v in values]
            rows = [r for r in rows if (r["part"], r["device"]) != (part, device)] + new_rows
            machine = {"gl": gl_description(ctx), "cpus": os.cpu_count(), "python": platform.python_version(),
                       "torch": torch.__version__, "torch_threads": torch.get_num_threads(),
                       "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else NOT_MEASURED,
                       "loadavg_before": load_before, "loadavg_after": os.getloadavg()}
            stamps[f"{part}/{device}"] = {"date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
                                          "machine": machine}
            write_json_atomic(cfg.out, _result(stamps, rows))
            bar.update(1)
    renderer.release()
    ctx.release()
    result = _result(stamps, rows)
    publish(result, cfg.out, markdown_table(result), cfg.docs, "gpu")


if __name__ == "__main__":
    main(tyro.cli(GpuBenchConfig))
