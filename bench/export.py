"""3DGS PLY export and playback benchmark: ``atgs-export`` of a trained checkpoint (time, size),
opening the folder in the player (every header checked), reading one file against decoding the
frame from the checkpoint, and the round trip: the folder and the checkpoint drawn by the player
headless for the same frames and cameras.

    python bench/export.py --checkpoint runs/mine/ckpt.pt   # writes bench/results/export.json, docs/export.md table
"""

from __future__ import annotations

import math
import os
import platform
import shutil
import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro

import atgs
from atgs.export import export_ply_sequence
from atgs.io.gaussian_ply import read_gaussian_ply
from atgs.threads import torch_threads
from atgs.timeline import evenly_spaced
from _docs import publish  # bench/_docs.py (the script's own folder is on sys.path)


@dataclass
class BenchConfig:
    checkpoint: Path = Path("/tmp/ply/cpu-fast-300/ckpt.pt")
    """A trained ckpt.pt (atgs-train output)."""
    repeats: int = 2
    """Exports of every frame to time."""
    views: int = 4
    """Frames (evenly spaced) x every third training camera compared in the round trip."""
    out: Path = Path("bench/results/export.json")
    docs: Path | None = Path("docs/export.md")
    """Markdown file with the bench:export markers to update (None: skip)."""


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 10 * math.log10(1.0 / max(mse, 1e-20))


def _median_ms(fn, items) -> float:
    ts = []
    for x in items:
        t0 = time.perf_counter()
        fn(x)
        ts.append(time.perf_counter() - t0)
    return 1000 * statistics.median(ts)


def run(cfg: BenchConfig) -> dict:
    from atgs.headless_gl import create_headless_context
    from atgs.viewer.loading import load_source
    from atgs.viewer.source import decode_frame
    from atgs.viewer.splat_renderer import RenderSettings, SplatRenderer

    load_before = os.getloadavg()
    model = atgs.load(cfg.checkpoint)
    F = model.num_frames
    scratch = Path(tempfile.mkdtemp(prefix="atgs-bench-export-"))
    try:
        export_s = []
        for i in range(cfg.repeats):
            t0 = time.perf_counter()
            res = export_ply_sequence(model, scratch / f"plys{i}", list(range(F)), progress=True)
            export_s.append(time.perf_counter() - t0)
        folder = res.out
        size = sum(p.stat().st_size for p in folder.iterdir())
        t0 = time.perf_counter()
        plys = load_source(folder)
        open_ms = 1000 * (time.perf_counter() - t0)
        sample = evenly_spaced(F, min(F, 10))
        with torch.no_grad(), torch_threads(1):  # as the player's decode thread
            read_ms = _median_ms(lambda f: read_gaussian_ply(plys.frame_file(f)), sample)
            decode_ms = _median_ms(model.gaussians_at_frame, sample)
        ctx = create_headless_context("auto")
        renderer = SplatRenderer(ctx, near=model.near)  # both drawn as the players draw the model
        settings = RenderSettings(exact_sort=True)
        psnrs = []
        for f in evenly_spaced(F, cfg.views):
            a, b = decode_frame(model, f), decode_frame(plys, f)
            for cam in model.cameras[::3]:
                renderer.set_gaussians(a)
                ref = renderer.render_image(cam, settings)
                renderer.set_gaussians(b)
                psnrs.append(_psnr(renderer.render_image(cam, settings), ref))
        renderer.release()
        ctx.release()
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return {
        "checkpoint": str(cfg.checkpoint), "frames": F, "gaussians_per_frame_mean": sum(res.gaussians) / F,
        "export_s": export_s, "export_ms_per_frame": [1000 * s / F for s in export_s],
        "folder_bytes": size, "open_folder_ms": open_ms, "read_file_median_ms": read_ms,
        "checkpoint_decode_median_ms": decode_ms,
        "round_trip_psnr_db": {"views": len(psnrs), "min": min(psnrs), "median": statistics.median(psnrs),
                               "size": [model.cameras[0].width, model.cameras[0].height]},
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "torch": torch.__version__,
                    "loadavg_before": load_before, "loadavg_after": os.getloadavg()},
        "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
    }


def markdown_table(r: dict) -> str:
    m, rt = r["machine"], r["round_trip_psnr_db"]
    exp = " / ".join(f"{s:.1f} s ({ms:.0f} ms per frame)" for s, ms in zip(r["export_s"], r["export_ms_per_frame"]))
    return "\n".join([
        f"Measured {r['date']} with `python bench/export.py --checkpoint {r['checkpoint']}` on {m['cpus']} CPUs, "
        f"load average {m['loadavg_before'][0]:.1f} before, {m['loadavg_after'][0]:.1f} after.", "",
        "| what | measured |", "|---|---|",
        f"| checkpoint | {r['frames']} frames, {r['gaussians_per_frame_mean']:,.0f} Gaussians per frame |",
        f"| export of every frame (decode + write, one torch thread), each run | {exp} |",
        f"| folder size | {r['folder_bytes'] / 2**20:.0f} MiB ({r['folder_bytes'] / r['frames'] / 2**20:.2f} MiB per frame) |",
        f"| open the folder in the player (every header checked) | {r['open_folder_ms']:.0f} ms |",
        f"| one frame: read the PLY / decode the checkpoint (median, one torch thread) | "
        f"{r['read_file_median_ms']:.1f} ms / {r['checkpoint_decode_median_ms']:.1f} ms |",
        f"| round trip: folder vs checkpoint drawn by the player, {rt['views']} views at "
        f"{rt['size'][0]}x{rt['size'][1]} | min {rt['min']:.1f} dB, median {rt['median']:.1f} dB |",
    ])


def main(cfg: BenchConfig) -> None:
    if not cfg.checkpoint.is_file():
        raise SystemExit(f"bench/export.py: --checkpoint {cfg.checkpoint} does not exist; train one with "
                         "atgs-train and pass its ckpt.pt")
    result = run(cfg)
    publish(result, cfg.out, markdown_table(result), cfg.docs, "export")


if __name__ == "__main__":
    main(tyro.cli(BenchConfig))
