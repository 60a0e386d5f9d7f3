"""Frame rate of the real player window (glfw + imgui, 640x480), as a user sees it.

    python bench/viewer_window.py                          # demo scene; xvfb-run if there is no display
    python bench/viewer_window.py --checkpoint ckpt.pt     # + a trained model, first loop and cached

Plays with the camera orbiting slowly (so every UI frame sorts and splats), the window's
default adaptive resolution and its 60 FPS cap, through ``PlayerApp.step`` exactly as
``atgs-view`` runs it. Per row: UI frames per second over the measured frames, median and 90th
percentile frame time, the overlay's smoothed splat (draw) time, the mean splatting resolution
factor, and how many distinct video frames were shown. Writes bench/results/viewer_window.json
and the table in docs/viewer.md. On this machine the display is Xvfb (software X server on the
same 2 cores).
"""

from __future__ import annotations

import json
import os
import sys
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro
from _docs import publish  # bench/_docs.py (the script's own folder is on sys.path)

from atgs.viewer.app import PlayerApp, rest_until
from atgs.viewer.loading import load_source


@dataclass
class WindowBenchConfig:
    checkpoint: Path | None = None
    """A trained ckpt.pt: adds its streaming rows (first loop, then with every frame cached)."""
    size: str = "640x480"
    decode: str = "torch"
    """The checkpoint's frames: torch (decode thread, cache) or gl (compute-shader decode, --decode gl)."""
    frames: int = 120
    """UI frames measured per row (after 30 to settle the adaptive resolution)."""
    out: Path = Path("bench/results/viewer_window.json")
    docs: Path | None = Path("docs/viewer.md")


def play(app: PlayerApp, frames: int, warm: int = 30) -> dict:
    """Play with an orbiting camera, paced like ``PlayerApp.run``; measure after ``warm`` frames."""
    app.playback.playing = True
    times, shown, scales = [], [], []
    last = time.perf_counter()
    for i in range(warm + frames):
        now = time.perf_counter()
        dt, last = now - last, now
        app.control.orbit(0.01, 0.0)
        app.step(min(dt, 0.25))
        if i >= warm:
            times.append((time.perf_counter() - now) * 1e3)
            scales.append(app._last_scale)
            if app.feeder.shown is not None:
                shown.append(app.feeder.shown.frame)
            if i == warm:
                t_start = now
        rest_until(now + 1.0 / 60.0)
    wall = time.perf_counter() - t_start
    return {
        "fps": frames / wall, "frame_ms_median": float(np.median(times)),
        "frame_ms_p90": float(np.percentile(times, 90)), "splat_ms": app.stats.draw_ms,
        "sort_ms": app.stats.sort_ms, "mean_scale": float(np.mean(scales)),
        "distinct_frames_shown": len(set(shown)), "frames_measured": frames,
    }  # fmt: skip


def run_rows(cfg: WindowBenchConfig) -> list[dict]:
    rows = []
    sources = [("demo", "built-in demo scene (atgs-view demo)")]
    if cfg.checkpoint is not None:
        sources.append((str(cfg.checkpoint), str(cfg.checkpoint)))
    for spec, name in sources:
        source = load_source(spec, 20000)
        decode = "torch" if spec == "demo" else cfg.decode  # the demo has nothing to decode
        app = PlayerApp(source, size=cfg.size, decode=decode)
        try:
            deadline = time.monotonic() + 120
            while app.feeder.shown is None and time.monotonic() < deadline:
                app.step(0.0)
                time.sleep(0.01)
            gl = app.gl_info
            variants = [("streaming decode", None)]
            if spec == "demo":
                variants.append(("UI hidden", "hide"))
            elif decode == "gl":  # no cache: every frame is decoded on the GL when it is shown
                variants = [("decoded on the GL (--decode gl)", None)]
            else:
                variants.append(("every frame cached (second loop)", "cached"))
            for label, how in variants:
                if how == "hide":
                    app.show_ui = False
                if how == "cached":  # keep playing until the whole sequence is in the cache
                    deadline = time.monotonic() + 600
                    while len(app.cache.cached_frames()) < source.num_frames and time.monotonic() < deadline:
                        play(app, 30, warm=0)
                load = os.getloadavg()
                row = {"scene": f"{name} ({source.num_frames} frames)", "mode": label, "size": cfg.size,
                       "gaussians": app.renderer.count,
                       "gl": gl, "loadavg_before": load, **play(app, cfg.frames), "loadavg_after": os.getloadavg()}
                print(json.dumps(row), flush=True)
                rows.append(row)
                app.show_ui = True
        finally:
            app.close()
    return rows


def markdown_table(result: dict) -> str:
    lines = [
        f"Measured {result['date']} on {result['cpus']} CPUs, {result['gl']}, in an Xvfb window "
        f"(`bench/viewer_window.py`, {result['frames']} UI frames per row after 30 to settle).",
        "",
        "| scene | mode | Gaussians | FPS | frame ms median / p90 | splat ms | res. factor | distinct frames shown | load before / after |",
        "|---|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in result["rows"]:
        lines.append(
            f"| {r['scene']} | {r['mode']} | {r['gaussians']:,} | **{r['fps']:.1f}** "
            f"| {r['frame_ms_median']:.0f} / {r['frame_ms_p90']:.0f} | {r['splat_ms']:.0f} | {r['mean_scale']:.2f} "
            f"| {r['distinct_frames_shown']} / {r['frames_measured']} "
            f"| {r['loadavg_before'][0]:.1f} / {r['loadavg_after'][0]:.1f} |"
        )
    return "\n".join(lines)


def main(cfg: WindowBenchConfig) -> None:
    if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
        if shutil.which("xvfb-run") is None:
            sys.exit("bench/viewer_window.py: no display and no xvfb-run; install xvfb (apt-get install xvfb)")
        cmd = ["xvfb-run", "-a", "-s", "-screen 0 1280x1024x24", sys.executable, *sys.argv]
        sys.exit(subprocess.call(cmd))
    rows = run_rows(cfg)
    result = {
        "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()), "cpus": os.cpu_count(),
        "gl": rows[0]["gl"] if rows else "?", "frames": cfg.frames, "rows": rows,
    }  # fmt: skip
    publish(result, cfg.out, markdown_table(result), cfg.docs, "viewer-window")


if __name__ == "__main__":
    main(tyro.cli(WindowBenchConfig))
