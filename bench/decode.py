"""Decode benchmark: time of ``model.gaussians_at_frame(f)`` (cached inference path,
atgs/model/fast_decode.py) against the uncached training-path decode, on a trained checkpoint.

    python bench/decode.py --checkpoint /tmp/quick_cpu/ckpt.pt   # writes bench/results/decode.json

Measured: the reference decode on a sample of frames; the fast path's first frame (builds the
per-anchor cache), sequential playback of every frame (new hash time slices are built when
playback crosses a time vertex), a second pass (all slices cached) and random scrubbing; and the
largest difference between the two paths (opacity threshold off, so both return the same set).
"""

from __future__ import annotations

import os
import platform
import random
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import tyro

import atgs
from atgs.model.fast_decode import InferenceCache
from atgs.progress import progress_bar
from atgs.timeline import evenly_spaced
from _docs import publish  # bench/_docs.py (the script's own folder is on sys.path)

FIELDS = ("means", "quats", "scales", "opacities", "colors")


@dataclass
class BenchConfig:
    checkpoint: Path = Path("/tmp/quick_cpu/ckpt.pt")
    """A trained ckpt.pt (atgs-train output)."""
    reference_frames: int = 12
    """Frames (evenly spaced) decoded with the slow reference path."""
    threads: tuple[int, ...] = (1, 2)
    """torch thread counts to measure (2-thread OpenMP suffers badly when another process holds a core)."""
    out: Path = Path("bench/results/decode.json")
    docs: Path | None = Path("docs/model.md")
    """Markdown file with the bench:decode markers to update (None: skip)."""


def _ms(ts: list[float]) -> dict[str, float]:
    return {"median_ms": 1000 * statistics.median(ts), "mean_ms": 1000 * statistics.fmean(ts),
            "max_ms": 1000 * max(ts)}


def _timed(fn, frames: list[int], desc: str) -> list[float]:
    ts = []
    with progress_bar(len(frames), desc, unit="frame") as bar:
        for f in frames:
            t0 = time.perf_counter()
            fn(f)
            ts.append(time.perf_counter() - t0)
            bar.update(1)
    return ts


def run(cfg: BenchConfig, threads: int) -> dict:
    torch.set_num_threads(threads)
    load_before = os.getloadavg()
    model = atgs.load(cfg.checkpoint)
    F = model.num_frames
    sample = evenly_spaced(F, cfg.reference_frames)
    ref = _timed(model.gaussians_at_frame_reference, sample, "reference decode")
    model.inference_cache = InferenceCache()
    t0 = time.perf_counter()
    g0 = model.gaussians_at_frame(0)
    first = time.perf_counter() - t0
    seq = _timed(model.gaussians_at_frame, list(range(F)), "fast decode, playback")
    warm = _timed(model.gaussians_at_frame, list(range(F)), "fast decode, 2nd pass")
    order = list(range(F))
    random.Random(0).shuffle(order)
    model.inference_cache = InferenceCache()
    model.gaussians_at_frame(0)
    scrub = _timed(model.gaussians_at_frame, order, "fast decode, scrubbing")
    # Accuracy: both paths without the opacity threshold (round-off can flip a Gaussian at it).
    thr, model.cfg.opacity_threshold = model.cfg.opacity_threshold, 0.0
    diff = {k: 0.0 for k in FIELDS}
    for f in sample:
        a, b = model.gaussians_at_frame(f), model.gaussians_at_frame_reference(f)
        for k in FIELDS:
            diff[k] = max(diff[k], float((getattr(a, k) - getattr(b, k)).abs().max()))
    model.cfg.opacity_threshold = thr
    return {
        "checkpoint": str(cfg.checkpoint), "anchors": model.num_anchors, "frames": F,
        "segments": model.num_segments, "gaussians_frame0": int(g0.means.shape[0]),
        "reference": {**_ms(ref), "frames": sample},
        "fast_first_frame_ms": 1000 * first,
        "fast_playback": _ms(seq), "fast_second_pass": _ms(warm), "fast_scrub": _ms(scrub),
        "max_abs_diff": diff,
        "machine": {"cpus": os.cpu_count(), "torch_threads": torch.get_num_threads(),
                    "python": platform.python_version(), "torch": torch.__version__,
                    "loadavg_before": load_before, "loadavg_after": os.getloadavg()},
        "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
    }


def markdown_table(results: list[dict]) -> str:
    r0 = results[0]
    lines = [f"Measured {r0['date']}, `{r0['checkpoint']}` ({r0['anchors']:,} anchors, {r0['frames']} frames, "
             f"{r0['segments']} segments, {r0['gaussians_frame0']:,} Gaussians at frame 0), "
             f"{r0['machine']['cpus']} CPUs.", "",
             "| torch threads | load avg before / after | decode | median ms | mean ms | max ms |",
             "|---:|---|---|---:|---:|---:|"]
    for r in results:
        m = r["machine"]
        la = f"{m['loadavg_before'][0]:.1f} / {m['loadavg_after'][0]:.1f}"
        rows = [("reference (training path, uncached)", r["reference"]),
                ("fast: playback, every frame", r["fast_playback"]),
                ("fast: second pass (all slices cached)", r["fast_second_pass"]),
                ("fast: random scrubbing", r["fast_scrub"])]
        for name, s in rows:
            lines.append(f"| {m['torch_threads']} | {la} | {name} | {s['median_ms']:.1f} | {s['mean_ms']:.1f} "
                         f"| {s['max_ms']:.1f} |")
    lines += [""] + [f"{r['machine']['torch_threads']} thread(s): first fast frame (builds the per-anchor cache) "
                     f"{r['fast_first_frame_ms']:.0f} ms; largest difference to the reference: "
                     + ", ".join(f"{k} {v:.1e}" for k, v in r["max_abs_diff"].items()) + "." for r in results]
    return "\n".join(lines)


def main(cfg: BenchConfig) -> None:
    if not cfg.checkpoint.is_file():
        raise SystemExit(f"bench/decode.py: --checkpoint {cfg.checkpoint} does not exist; train one with "
                         "atgs-train (e.g. atgs-train cpu) and pass its ckpt.pt")
    if not cfg.threads or min(cfg.threads) < 1:
        raise SystemExit(f"bench/decode.py: --threads {cfg.threads}: give one or more counts >= 1")
    result = [run(cfg, n) for n in cfg.threads]
    publish(result, cfg.out, markdown_table(result), cfg.docs, "decode")


if __name__ == "__main__":
    main(tyro.cli(BenchConfig))
