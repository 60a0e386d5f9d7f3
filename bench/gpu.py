"""GPU benchmark (issue 13): what a GPU buys end to end, with the device name on every row.

    python bench/gpu.py      # writes bench/results/gpu.json and the table in docs/viewer.md

Rows, one function each (``PARTS``; each returns a list of row dicts with a ``device``):
- viewer: FPS of the splatting player at 1920x1080 for 100k / 500k / 1M random Gaussians, for a
  new video frame (pack + upload + sort + draw, the Gaussians starting on the device) and for a
  camera move (sort + draw), with the stages' times;
- decode: ms per frame of an untrained ATGS model of the ``paper`` and ``cpu`` presets
  (``model.gaussians_at_frame`` + packing, i.e. what the player's decode thread does).
Each part runs on CUDA when torch sees a CUDA device and on the CPU; a CUDA row without a CUDA
device is written as ``"not measured"`` with the reason. The OpenGL draw runs wherever the
headless context lives (its renderer string is in ``machine.gl``: llvmpipe is the CPU).
"""

from __future__ import annotations

import sys

from _docs import publish  # noqa: E402  (bench/_docs.py, imported before the folder is dropped)
from _viewer_scenes import random_gaussians, time_frames, untrained_model, warm_renderer  # noqa: E402


import json
import os
import platform
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
import tyro

from atgs.headless_gl import gl_description
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
    parts: tuple[str, ...] = ("viewer", "decode")
    gl: str = "auto"
    out: Path = Path("bench/results/gpu.json")
    docs: Path | None = Path("docs/viewer.md")
    """Replace the table between the bench:gpu markers in this file (None: leave the docs alone)."""


def device_name(device: str) -> str:
    if device == "cuda":
        return torch.cuda.get_device_name(0)
    return f"CPU ({os.cpu_count()} cores, {platform.processor() or platform.machine()})"


def unavailable(device: str) -> str | None:
    """Why ``device`` cannot be measured here (None: it can)."""
    if device == "cuda" and not torch.cuda.is_available():
        return f"{NOT_MEASURED} (no CUDA device: torch {torch.__version__} sees none)"
    return None


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
        rows.append(row)
        print(json.dumps(row))
    return rows


def decode_rows(cfg: GpuBenchConfig, device: str, renderer: SplatRenderer) -> list[dict]:
    """ms per decoded + packed frame of an untrained model of each preset, on ``device``: the
    model moves there if it can (``to(device)``), else it decodes on the CPU and its Gaussians
    are packed on the device (the player does the same, viewer.device)."""
    from atgs.viewer.device import place_source

    rows = []
    for preset_name in cfg.presets:
        model = untrained_model(preset_name, cfg.decode_points)
        source = place_source(model, torch.device(device))
        where = device if (source is not model or device == "cpu") else "cpu (the model cannot move: no to())"
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


# Each part: name -> function(cfg, device, renderer) -> rows. Training steps/s is another part.
PARTS: dict[str, Callable[[GpuBenchConfig, str, SplatRenderer], list[dict]]] = {
    "viewer": viewer_rows,
    "decode": decode_rows,
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


def markdown_table(result: dict) -> str:
    m = result["machine"]
    lines = [f"Measured {result['date']}: {m['cpus']} CPUs, OpenGL {m['gl']}, torch {m['torch']}; "
             f"load average before: {', '.join(f'{x:.1f}' for x in m['loadavg_before'])}."]
    rows = result["rows"]
    lines += part_table(
        [r for r in rows if r["part"] == "viewer"],
        ["viewer at 1920x1080: device", "name", "Gaussians", "pack ms", "upload ms", "sort ms", "draw ms",
         "new frame FPS", "camera move FPS"], "gaussians",
        lambda r: [f"{r['pack_ms']:.1f}", f"{r['upload_ms']:.1f}", f"{r['sort_ms']:.1f}", f"{r['draw_ms']:.0f}",
                   f"**{r['fps_new_frame']:.2f}**", f"**{r['fps_camera_move']:.2f}**"])
    lines += part_table(
        [r for r in rows if r["part"] == "decode"],
        ["decode + pack, untrained model: device", "name", "preset", "decoded on", "anchors", "Gaussians",
         "first frame ms", "ms per frame"], "preset",
        lambda r: [r["decoded_on"], f"{r['anchors']:,}", f"{r['gaussians']:,}", f"{r['first_frame_ms']:.0f}",
                   f"**{r['decode_ms']:.1f}**"])
    return "\n".join(lines)


def main(cfg: GpuBenchConfig) -> None:
    load_before = os.getloadavg()
    ctx, renderer = warm_renderer(cfg.gl)
    rows: list[dict] = []
    # what an unmeasured part's rows would have covered (one "not measured" row each)
    row_keys = {"viewer": ("gaussians", cfg.counts), "decode": ("preset", cfg.presets)}
    jobs = [(part, device) for part in cfg.parts for device in cfg.devices]
    with progress_bar(len(jobs), "gpu bench", unit="part") as bar:
        for part, device in jobs:
            reason = unavailable(device)
            if reason is None:
                rows += PARTS[part](cfg, device, renderer)
            else:
                key, values = row_keys.get(part, ("case", ("all",)))
                rows += [{"part": part, "device": device, "device_name": "none", key: v, "status": reason}
                         for v in values]
            bar.update(1)
    result = {
        "machine": {"gl": gl_description(ctx), "cpus": os.cpu_count(), "python": platform.python_version(),
                    "torch": torch.__version__, "torch_threads": torch.get_num_threads(),
                    "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else NOT_MEASURED,
                    "loadavg_before": load_before, "loadavg_after": os.getloadavg()},
        "rows": rows,
        "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
    }  # fmt: skip
    renderer.release()
    ctx.release()
    publish(result, cfg.out, markdown_table(result), cfg.docs, "gpu")


if __name__ == "__main__":
    main(tyro.cli(GpuBenchConfig))
