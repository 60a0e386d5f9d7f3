"""What one CPU training step costs, and what buys more images per second.

    python bench/step.py                  # every case, 2 and 1 torch threads (~6 min)
    python bench/step.py --threads 2

The built-in large-motion scene (prepared, 6 keyframes, dense stereo points), preset `cpu`,
untrained model (24k anchors, ~11k of them in a view). Each case times `Trainer.train_step()`
(decode, rasterize, loss, backward, optimizer steps; densification off so the model stays the
same size) over `steps` steps after `warmup` steps, the cases taking turns (`rounds` turns: a
machine's speed drifts by more than some cases differ), and reports seconds per step and training
images per second:

- grids `torch`: the spatial and hash grids as torch gathers (the reference implementation);
- grids `compiled`: the same lookups as compiled kernels (atgs/render/csrc/grids.cpp), the default;
- `torch sparse Adam`: the sparse tables' update in torch ops (`SparseAdam` backend "torch",
  its reference) instead of the compiled step (atgs/render/csrc/sparse_adam.cpp), the default;
- `cameras_per_frame` 2, 3: one decode of a frame rendered from that many cameras.

Results: bench/results/step.json and the bench:step table in docs/training.md.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
import tyro
from _docs import loadavg, publish, run_stamp  # bench/ (the script's own folder is on sys.path)
from _harness import build_trainer, timed_steps

from atgs.data.scene import PreparedScene
from atgs.data.synth.videos import ensure_default_scene
from atgs.io.cache import cache_dir
from atgs.train.trainer import Trainer

ROOT = Path(__file__).resolve().parent.parent
CASES = {  # name: (grid backend, cameras per frame, sparse Adam backend)
    "torch grids": ("torch", 1, "auto"),
    "compiled grids, torch sparse Adam": ("auto", 1, "torch"),
    "compiled grids": ("auto", 1, "auto"),
    "compiled, 2 cameras/frame": ("auto", 2, "auto"),
    "compiled, 3 cameras/frame": ("auto", 3, "auto"),
}


@dataclass
class StepBench:
    threads: tuple[int, ...] = (2, 1)
    steps: int = 40
    rounds: int = 5  # the steps are taken in turns across the cases (see run_cases)
    warmup: int = 5
    cache: Path = field(default_factory=cache_dir)
    work_dir: Path = Path("/tmp/atgs-bench-step")
    out: Path = ROOT / "bench" / "results" / "step.json"
    docs: Path = ROOT / "docs" / "training.md"


def make_trainer(scene, name: str, threads: int, args: StepBench) -> Trainer:
    backend, cams, optim = CASES[name]
    tr = build_trainer(scene, args.work_dir / name.replace(" ", "_").replace("/", "_"), "cpu", iterations=1000,
                       train={"densify.enabled": False, "cameras_per_frame": cams}, threads=threads)
    tr.model.hash.backend = tr.model.spatial.backend = backend
    tr.sparse_opt.backend = optim
    for _ in range(args.warmup):
        tr.train_step()
    return tr


def _timed(fn, into: dict, key: str):
    def timed(*a, **k):
        t0 = time.perf_counter()
        out = fn(*a, **k)
        into[key] += time.perf_counter() - t0
        return out
    return timed


def run_cases(scene, threads: int, args: StepBench) -> list[dict]:
    """Every case's steps, taken in turns (``rounds`` turns of steps / rounds steps each), so
    that a machine getting slower or faster during the bench weighs on every case alike."""
    torch.set_num_threads(threads)
    trainers = {name: make_trainer(scene, name, threads, args) for name in CASES}
    seconds, update = dict.fromkeys(CASES, 0.0), dict.fromkeys(CASES, 0.0)
    for name, tr in trainers.items():  # the sparse tables' update alone (the optimizer cases differ only there)
        tr._apply_sparse = _timed(tr._apply_sparse, update, name)
    per_turn = max(1, args.steps // args.rounds)
    for _ in range(args.rounds):
        for name, tr in trainers.items():
            seconds[name] += timed_steps(tr, per_turn)[1]
    rows = []
    for name, tr in trainers.items():
        backend, cams, optim = CASES[name]
        sec = seconds[name] / (per_turn * args.rounds)
        rows.append({"case": name, "threads": threads, "grids": backend, "cameras_per_frame": cams,
                     "sparse_adam": optim, "seconds_per_step": sec, "images_per_second": cams / sec,
                     "sparse_update_seconds": update[name] / (per_turn * args.rounds),
                     "anchors": tr.model.num_anchors, "steps": per_turn * args.rounds,
                     "loadavg": loadavg()})
    return rows


def table(rows: list[dict]) -> str:
    lines = ["| case | torch threads | s / step | images / s | vs torch grids | sparse update, ms / step |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        base = next(b for b in rows if b["threads"] == r["threads"] and b["case"] == "torch grids")
        gain = r["images_per_second"] / base["images_per_second"]
        lines.append(f"| {r['case']} | {r['threads']} | {r['seconds_per_step']:.3f} | {r['images_per_second']:.2f} "
                     f"| {gain:.2f}x | {1000 * r['sparse_update_seconds']:.1f} |")
    lo = min(min(r["loadavg"]) for r in rows)
    hi = max(max(r["loadavg"]) for r in rows)
    lines.append("")
    lines.append(f"Preset cpu, built-in large-motion scene (256x192, {rows[0]['anchors']:,} anchors, densification "
                 f"off), mean of {rows[0].get('steps', '')} steps after warm-up, the cases taking turns; load average "
                 f"{lo:.1f}-{hi:.1f}.")
    return "\n".join(lines)


def main() -> None:
    args = tyro.cli(StepBench)
    scene = PreparedScene.load(ensure_default_scene(args.cache, keyframes=6, progress=True))
    rows = []
    for threads in args.threads:
        for r in run_cases(scene, threads, args):
            print(r, flush=True)
            rows.append(r)
    result = {"rows": rows, **run_stamp(load=False), "machine": {"cpus": os.cpu_count()}}
    publish(result, args.out, table(rows), args.docs, "step")


if __name__ == "__main__":
    main()
