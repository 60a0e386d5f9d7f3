"""Viewer benchmark: decode, sort, upload, draw times and FPS of the GLSL splatting player on
this machine's software OpenGL (llvmpipe through EGL).

    python bench/viewer.py                       # writes bench/results/viewer.json
    python bench/viewer.py --checkpoint ckpt.pt  # playback of a real model at 640x480
    python bench/viewer.py --parts counts        # part 1 only (with its before/after comparison)

Part 1: N random Gaussians (10k, 50k, 200k, 1M) seen by a 1280x720 camera: per-stage times of a
frame whose Gaussians change (pack + sort + upload + draw) and of a static frame with a
moving camera (sort + draw); the same measurement of the code at ``--before`` (a git commit:
its viewer, shaders and atgs packages are exported to a temporary folder and timed by this
script in a subprocess, count by count right after the current code, at about the same load).
Part 2: playback at 640x480 through the real player pipeline (background decode cache ->
upload -> sort -> draw) for a model-sized scene: the given checkpoint, else an untrained
ATGS model with the "cpu" preset (decoding a real network; its Gaussians have the sizes an
initialised model has), and the built-in demo scene.
"""

from __future__ import annotations

import sys

from _docs import update_docs_table, write_json_atomic  # noqa: E402  (bench/_docs.py, imported first)
from _viewer_scenes import bench_camera, random_gaussians, time_frames, untrained_model, warm_renderer  # noqa: E402


import json
import math
import os
import platform
import statistics
import subprocess
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
import tyro

from atgs.cameras import Camera
from atgs.headless_gl import gl_description
from atgs.progress import progress_bar
from atgs.viewer.adaptive import next_render_scale
from atgs.viewer.decode_cache import DecodeCache
from atgs.viewer.gl_sync import gil_free_finish
from atgs.viewer.packing import PackedGaussians
from atgs.viewer.playback import FrameFeeder, Playback
from atgs.viewer.source import GaussianSource, SyntheticSource, decode_frame
from atgs.viewer.splat_renderer import ALPHA_MIN, RenderSettings, SplatRenderer


@dataclass
class BenchConfig:
    counts: tuple[int, ...] = (10_000, 50_000, 200_000, 1_000_000)
    size: tuple[int, int] = (1280, 720)
    repeats: int = 3
    playback_size: tuple[int, int] = (640, 480)
    playback_frames: int = 40
    checkpoint: Path | None = None
    """A trained ckpt.pt for the playback part (default: an untrained 'cpu'-preset model)."""
    gl: str = "egl"
    out: Path = Path("bench/results/viewer.json")
    target_dtypes: tuple[str, ...] = ("f4", "f1")
    """Render targets: f4 = float32 (headless/tests), f1 = RGBA8 (the player window, color mode)."""
    docs: Path | None = Path("docs/viewer.md")
    """Replace the table between the bench markers in this file (None: leave the docs alone)."""
    cutoffs: tuple[int, ...] = (1, 2, 4, 8)
    """Alpha cutoffs (in 1/255) of the speed / quality table (1 = the rasterizer's rule)."""
    cutoff_repeats: int = 5
    parts: tuple[str, ...] = ("counts", "before", "playback", "cutoffs")
    """What to measure: counts (part 1), before (with counts: part 1 also on the code at
    --before, count by count right after this code), playback (part 2), cutoffs (part 3)."""
    before: str = "4f73495"
    """Git commit of the code to compare with in part 1 (the viewer before the compact GPU layout)."""


def _median(xs: list[float]) -> float:
    return float(statistics.median(xs)) if xs else 0.0


def bench_counts(cfg: BenchConfig, renderer: SplatRenderer, dtype: str) -> list[dict]:
    renderer.target_dtype = dtype
    rows = []
    W, H = cfg.size
    for n in cfg.counts:
        row = {"gaussians": n, "target": dtype, "size": f"{W}x{H}",
               **time_frames(renderer, random_gaussians(n), W, H, cfg.repeats), "loadavg": os.getloadavg()}
        rows.append(row)
        print(json.dumps(row))
    return rows


def preload_all(source: GaussianSource) -> dict[int, PackedGaussians]:
    out = {}
    with progress_bar(source.num_frames, "preloading frames", unit="frame") as bar:
        for f in range(source.num_frames):
            out[f] = decode_frame(source, f)
            bar.update(1)
    return out


def bench_playback(source: GaussianSource, name: str, cfg: BenchConfig, renderer: SplatRenderer,
                   preload: bool = False, adaptive: bool = False, min_alpha: float = ALPHA_MIN,
                   pinned: dict[int, PackedGaussians] | None = None) -> dict:
    """Wall-clock playback through the player's pipeline: feeder/cache (background decode),
    upload on change, sort + draw every frame, camera slowly orbiting (so the sort runs).
    Each frame waits for the GL with the GIL released, as the window does (see gil_free_finish).
    ``adaptive``: the window's adaptive-resolution rule (viewer.adaptive.next_render_scale)
    on the splat time alone, since there is no present or UI here (the window budgets its whole
    frame; bench/viewer_window.py measures that), after 20 unmeasured frames to settle;
    otherwise always the full playback size. ``pinned``: frames decoded before
    (reused across --preload rows)."""
    # osmesa contexts are not libglvnd's: a ctypes glFinish would not wait for them
    finish = gil_free_finish(renderer.ctx.finish) if cfg.gl == "egl" else renderer.ctx.finish
    W, H = cfg.playback_size
    cams = list(source.cameras)
    base = cams[0] if cams else bench_camera(W, H)
    sx, sy = W / base.width, H / base.height
    K = base.K.copy()
    K[0] *= sx
    K[1] *= sy
    renderer.target_dtype = "f1"  # what the player window uses in color mode
    decode_ms = [decode_frame(source, f).decode_ms for f in (0, 1)]
    n_gauss = len(decode_frame(source, 0))
    pb = Playback(num_frames=source.num_frames, fps=float(source.fps or 30.0), playing=True)
    shown = []
    scale, scales = 1.0, []
    settings = RenderSettings(min_alpha=min_alpha)
    load_before = os.getloadavg()
    if preload and pinned is None:
        pinned = preload_all(source)
    elif not preload:
        pinned = None
    warm = 20 if adaptive else 0
    with DecodeCache(lambda f: decode_frame(source, f), capacity=8, pinned=pinned) as cache:
        feeder = FrameFeeder(cache, lookahead=4)
        cache.wait_for(0, timeout=120)
        t_start = time.perf_counter()
        last = t_start
        draw, sort = [], []
        for i in range(warm + cfg.playback_frames):
            if i == warm:  # measure from here
                t_start = last = time.perf_counter()
                draw, sort, shown, scales = [], [], [], []
            now = time.perf_counter()
            pb.advance(now - last)
            last = now
            packed, changed = feeder.update(pb)
            if changed and packed is not None:
                renderer.set_gaussians(packed)
            if packed is not None:
                shown.append(packed.frame)
            a = 0.01 * i
            R = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1.0]])
            w2c = base.w2c.copy()
            w2c[:3, :3] = base.w2c[:3, :3] @ R.T
            rw, rh = max(1, int(W * scale)), max(1, int(H * scale))
            Ks = K.copy()
            Ks[0] *= rw / W
            Ks[1] *= rh / H
            cam = Camera("p", rw, rh, Ks, w2c)
            renderer.render(cam, settings, sync=False)
            t_wait = time.perf_counter()
            finish()  # draw = issuing the draw + waiting for it, as the window measures it
            draw.append(renderer.timings.draw_ms + (time.perf_counter() - t_wait) * 1e3)
            sort.append(renderer.timings.sort_ms)
            scales.append(scale)
            if adaptive:
                scale = next_render_scale(scale, draw[-1])
        wall = time.perf_counter() - t_start
    mode = (" (--preload" if preload else " (streaming decode") + (", adaptive resolution)" if adaptive else ")")
    row = {
        "scene": name + mode, "size": f"{W}x{H}", "gaussians": n_gauss,
        "min_alpha_255": round(min_alpha * 255, 3), "adaptive": adaptive,
        "mean_scale": float(np.mean(scales)), "last_scale": scales[-1],
        "loadavg_before": load_before, "loadavg_after": os.getloadavg(),
        "decode_ms": _median(decode_ms), "sort_ms": _median(sort), "draw_ms": _median(draw),
        "fps": cfg.playback_frames / wall, "distinct_frames_shown": len(set(shown)),
        "frames_rendered": cfg.playback_frames, "source_fps": float(source.fps or 30.0),
    }  # fmt: skip
    print(json.dumps(row))
    return row



def bench_cutoffs(source: GaussianSource, name: str, cfg: BenchConfig, renderer: SplatRenderer) -> list[dict]:
    """Speed / quality of the alpha cutoff on frame 0 from the first camera at the playback
    size: splats drawn, draw time (RGBA8 target, as the window) and PSNR of the float image
    against the default cutoff 1/255 (same sort, so only the cutoff differs)."""
    finish = gil_free_finish(renderer.ctx.finish) if cfg.gl == "egl" else renderer.ctx.finish
    W, H = cfg.playback_size
    cams = list(source.cameras)
    base = cams[0] if cams else bench_camera(W, H)
    K = base.K.copy()
    K[0] *= W / base.width
    K[1] *= H / base.height
    cam = Camera("c", W, H, K, base.w2c)
    renderer.set_gaussians(decode_frame(source, 0))
    rows, ref = [], None
    for c in cfg.cutoffs:
        s = RenderSettings(min_alpha=c / 255.0)
        renderer.target_dtype = "f4"
        img = renderer.render_image(cam, s)
        if ref is None:
            ref = img
        mse = float(np.mean((img.astype(np.float64) - ref) ** 2))
        renderer.target_dtype = "f1"
        renderer.render(cam, s, sync=True)
        ms = []
        for _ in range(cfg.cutoff_repeats):
            t0 = time.perf_counter()
            renderer._sort_key.version = -1  # redo the cull + sort too: the full per-view cost
            renderer.render(cam, s, sync=False)
            finish()
            ms.append((time.perf_counter() - t0) * 1e3)
        row = {
            "scene": name, "size": f"{W}x{H}", "min_alpha_255": c, "drawn": renderer.timings.drawn,
            "ms": _median(ms), "psnr_db": 10 * math.log10(1.0 / max(mse, 1e-20)) if mse > 0 else float("inf"),
            "max_abs_diff": float(np.abs(img - ref).max()), "loadavg": os.getloadavg(),
        }  # fmt: skip
        print(json.dumps(row))
        rows.append(row)
    return rows


def bench_before(cfg: BenchConfig, counts: tuple[int, ...], tree: Path) -> list[dict]:
    """Part 1 for ``counts`` timed on the code of commit ``cfg.before``, exported to ``tree``
    (:func:`export_before`): this script runs with ``--parts counts`` and that folder first on
    PYTHONPATH (its part 1 uses only APIs both versions have)."""
    root = Path(__file__).resolve().parent.parent
    out = tree / "before.json"
    args = [sys.executable, str(Path(__file__).resolve()), "--parts", "counts", "--out", str(out),
            "--docs", "None", "--gl", cfg.gl, "--repeats", str(cfg.repeats),
            "--counts", *map(str, counts), "--target-dtypes", *cfg.target_dtypes]
    subprocess.run(args, check=True, env={**os.environ, "PYTHONPATH": os.pathsep.join([str(tree), str(root)])})
    rows = json.loads(out.read_text())["per_count"]
    out.unlink()
    for r in rows:
        r["code"] = cfg.before
    return rows


def export_before(ref: str, tree: Path) -> None:
    """``git archive`` of the atgs, viewer and shaders packages at ``ref`` into ``tree``."""
    root = Path(__file__).resolve().parent.parent
    archive = subprocess.run(["git", "-C", str(root), "archive", ref, "atgs", "viewer", "shaders"],
                             check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(tree)], input=archive, check=True)


def bench_counts_before_after(cfg: BenchConfig, renderer: SplatRenderer) -> tuple[list[dict], list[dict]]:
    """Part 1 for each count: this code, then (with "before" in cfg.parts) the code at
    cfg.before right after it, so that both see about the same load."""
    after: list[dict] = []
    before: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="atgs-viewer-before-") as tmp:
        if "before" in cfg.parts:
            export_before(cfg.before, Path(tmp))
        with progress_bar(len(cfg.counts), "viewer bench, part 1", unit="count") as bar:
            for n in cfg.counts:
                one = replace(cfg, counts=(n,))
                for dt in cfg.target_dtypes:
                    after += bench_counts(one, renderer, dt)
                if "before" in cfg.parts:
                    before += bench_before(cfg, (n,), Path(tmp))
                bar.update(1)
    order = {dt: i for i, dt in enumerate(cfg.target_dtypes)}
    key = lambda r: (order[r["target"]], r["gaussians"])  # noqa: E731  (the table's row order)
    return sorted(after, key=key), sorted(before, key=key)


def markdown_counts(result: dict) -> list[str]:
    """Part 1: before -> after per stage, and the speed-up of pack + sort + upload."""
    before = {(r["gaussians"], r["target"]): r for r in result.get("per_count_before", [])}
    lines = ["| Gaussians | target | pack ms | sort ms | upload ms | pack + sort + upload ms | draw ms "
             "| new frame FPS | camera move FPS |", "|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in result["per_count"]:
        b = before.get((r["gaussians"], r["target"]))
        psu = r["pack_ms"] + r["sort_ms"] + r["upload_ms"]

        def cell(key: str, fmt: str) -> str:
            return f"{b[key]:{fmt}} -> {r[key]:{fmt}}" if b else f"{r[key]:{fmt}}"

        if b:
            bpsu = b["pack_ms"] + b["sort_ms"] + b["upload_ms"]
            total = f"{bpsu:.0f} -> **{psu:.0f}** ({bpsu / psu:.1f}x)"
        else:
            total = f"**{psu:.0f}**"
        lines.append(f"| {r['gaussians']:,} | {r['target']} | {cell('pack_ms', '.1f')} | {cell('sort_ms', '.1f')} "
                     f"| {cell('upload_ms', '.1f')} | {total} | {cell('draw_ms', '.0f')} "
                     f"| {cell('fps_new_frame', '.2f')} | {cell('fps_camera_move', '.2f')} |")
    return lines


def machine_line(m: dict, date: str) -> str:
    la = lambda xs: ", ".join(f"{x:.1f}" for x in xs)  # noqa: E731
    return (f"Measured {date} on {m['cpus']} CPUs, {m['gl']}; load average before: {la(m['loadavg_before'])} "
            f"(after: {la(m['loadavg_after'])}).")


def counts_table(result: dict) -> str:
    """Part 1 (bench:viewer-counts in docs/viewer.md)."""
    lines = [machine_line(result["counts_machine"], result["counts_date"]), ""]
    if result.get("per_count_before"):
        lines += [f"Before -> after: the code at commit {result['before']} (texture of CPU-packed covariances, "
                  "numpy sort) -> this code (vertex columns, covariance in the shader, torch sort), each count "
                  "timed on this code and right after on that one.", ""]
    return "\n".join(lines + markdown_counts(result))


def playback_table(result: dict) -> str:
    """Parts 2 and 3 (bench:viewer in docs/viewer.md)."""
    lines = [machine_line(result["machine"], result["date"]), "",
             "| playback scene | size | Gaussians | cutoff | res. factor | decode ms | sort ms | draw ms | FPS "
             "| distinct frames shown | load before / after |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in result["playback"]:
        lines.append(
            f"| {r['scene']} | {r['size']} | {r['gaussians']:,} | {r['min_alpha_255']:g}/255 | {r['mean_scale']:.2f} "
            f"| {r['decode_ms']:.0f} | {r['sort_ms']:.1f} | {r['draw_ms']:.0f} | **{r['fps']:.1f}** "
            f"| {r['distinct_frames_shown']} / {r['frames_rendered']} "
            f"| {r['loadavg_before'][0]:.1f} / {r['loadavg_after'][0]:.1f} |"
        )
    lines += ["", "| alpha cutoff (frame 0, camera 0) | size | cutoff | splats drawn | cull + sort + draw ms "
              "| PSNR vs 1/255 | max abs diff | load |",
              "|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in result.get("cutoffs", []):
        lines.append(
            f"| {r['scene']} | {r['size']} | {r['min_alpha_255']}/255 | {r['drawn']:,} | {r['ms']:.0f} "
            f"| {r['psnr_db']:.1f} dB | {r['max_abs_diff']:.3f} | {r['loadavg'][0]:.1f} |"
        )
    return "\n".join(lines)


def main(cfg: BenchConfig) -> None:
    """Measures ``cfg.parts``; the results file keeps the figures of parts not measured now."""
    load_before = os.getloadavg()
    ctx, renderer = warm_renderer(cfg.gl)
    result: dict = json.loads(cfg.out.read_text()) if cfg.out.exists() else {}

    def machine() -> dict:
        return {"gl": gl_description(ctx), "cpus": os.cpu_count(), "python": platform.python_version(),
                "torch_threads": torch.get_num_threads(), "loadavg_before": load_before,
                "loadavg_after": os.getloadavg()}

    def now() -> str:
        return time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())

    if "counts" in cfg.parts:
        rows, before = bench_counts_before_after(cfg, renderer)
        result.update(per_count=rows, counts_machine=machine(), counts_date=now())
        result.pop("per_count_before", None)
        if before:
            result.update(per_count_before=before, before=cfg.before)
    if "playback" in cfg.parts or "cutoffs" in cfg.parts:
        if cfg.checkpoint is not None:
            import atgs

            model = atgs.load(cfg.checkpoint)
            name = f"{cfg.checkpoint} ({model.num_frames} frames)"
        else:
            model = untrained_model()
            name = "untrained ATGS model, cpu preset"
        demo = SyntheticSource(num_gaussians=20000, frames=120, image_size=(640, 480), num_cameras=6)
        demo_name = "built-in demo scene (atgs-view demo)"
    if "playback" in cfg.parts:
        playback = []
        # The built-in scene first: it is the aim's subject (25 FPS at 640x480).
        playback.append(bench_playback(demo, demo_name, cfg, renderer))
        playback.append(bench_playback(demo, demo_name, cfg, renderer, min_alpha=4 / 255))
        playback.append(bench_playback(demo, demo_name, cfg, renderer, adaptive=True))
        playback.append(bench_playback(model, name, cfg, renderer))
        pinned = preload_all(model)
        playback.append(bench_playback(model, name, cfg, renderer, preload=True, pinned=pinned))
        playback.append(bench_playback(model, name, cfg, renderer, preload=True, min_alpha=4 / 255, pinned=pinned))
        playback.append(bench_playback(model, name, cfg, renderer, preload=True, adaptive=True, pinned=pinned))
        del pinned
        result["playback"] = playback
    if "cutoffs" in cfg.parts:
        result["cutoffs"] = bench_cutoffs(demo, demo_name, cfg, renderer) + bench_cutoffs(model, name, cfg, renderer)
    if "playback" in cfg.parts or "cutoffs" in cfg.parts:
        result.update(machine=machine(), date=now())
    renderer.release()
    ctx.release()
    write_json_atomic(cfg.out, result)
    print(f"wrote {cfg.out}")
    for marker, table, measured in (("viewer-counts", counts_table, "counts" in cfg.parts),
                                    ("viewer", playback_table, "playback" in cfg.parts or "cutoffs" in cfg.parts)):
        if measured:
            text = table(result)
            print(text)
            if cfg.docs is not None:
                update_docs_table(cfg.docs, marker, text)


if __name__ == "__main__":
    main(tyro.cli(BenchConfig))
