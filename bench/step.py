"""What one CPU training step costs, and what buys more images per second.

    python bench/step.py                  # every case, 2 and 1 torch threads (~3 min)
    python bench/step.py --threads 2

The built-in large-motion scene (prepared, 6 keyframes, dense stereo points), preset `cpu`,
untrained model (24k anchors, ~11k of them in a view). Each case times `Trainer.train_step()`
(decode, rasterize, loss, backward, optimizer steps; densification off so the model stays the
same size) over `steps` steps after `warmup` steps, and reports seconds per step and training
images per second:

- grids `torch`: the spatial and hash grids as torch gathers (the reference implementation);
- grids `compiled`: the same lookups as compiled kernels (atgs/render/csrc/grids.cpp), the default;
- `cameras_per_frame` 2, 3: one decode of a frame rendered from that many cameras.

Results: bench/results/step.json and the bench:step table in docs/training.md.
"""

from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import tyro

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _docs import git_commit, publish  # noqa: E402

from atgs.data.scene import PreparedScene  # noqa: E402
from atgs.data.synth import ensure_default_scene  # noqa: E402
from atgs.io.cache import cache_dir  # noqa: E402
from atgs.train.config import preset  # noqa: E402
from atgs.train.trainer import Trainer  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
CASES = {  # name: (grid backend, cameras per frame)
    "torch grids": ("torch", 1),
    "compiled grids": ("auto", 1),
    "compiled, 2 cameras/frame": ("auto", 2),
    "compiled, 3 cameras/frame": ("auto", 3),
}


@dataclass
class StepBench:
    threads: tuple[int, ...] = (2, 1)
    steps: int = 20
    warmup: int = 5
    cache: Path = field(default_factory=cache_dir)
    work_dir: Path = Path("/tmp/atgs-bench-step")
    out: Path = ROOT / "bench" / "results" / "step.json"
    docs: Path = ROOT / "docs" / "training.md"


def run_case(scene, name: str, threads: int, args: StepBench) -> dict:
    backend, cams = CASES[name]
    m, t = preset("cpu", 1000)
    t.eval_every = t.save_every = 0
    t.densify.enabled = False
    t.threads, t.cameras_per_frame = threads, cams
    tr = Trainer(scene, m, t, args.work_dir / "run")
    tr.model.hash.backend = tr.model.spatial.backend = backend
    for _ in range(args.warmup):
        tr.train_step()
    t0 = time.perf_counter()
    for _ in range(args.steps):
        tr.train_step()
    sec = (time.perf_counter() - t0) / args.steps
    return {"case": name, "threads": threads, "grids": backend, "cameras_per_frame": cams,
            "seconds_per_step": sec, "images_per_second": cams / sec, "anchors": tr.model.num_anchors,
            "loadavg": list(os.getloadavg())}


def table(rows: list[dict]) -> str:
    lines = ["| case | torch threads | s / step | images / s | vs torch grids |", "|---|---|---|---|---|"]
    for r in rows:
        base = next(b for b in rows if b["threads"] == r["threads"] and b["case"] == "torch grids")
        gain = r["images_per_second"] / base["images_per_second"]
        lines.append(f"| {r['case']} | {r['threads']} | {r['seconds_per_step']:.3f} | {r['images_per_second']:.2f} "
                     f"| {gain:.2f}x |")
    lo = min(min(r["loadavg"]) for r in rows)
    hi = max(max(r["loadavg"]) for r in rows)
    lines.append("")
    lines.append(f"Preset cpu, built-in large-motion scene (256x192, {rows[0]['anchors']:,} anchors, densification "
                 f"off), mean of {rows[0].get('steps', '')} steps after warm-up; load average {lo:.1f}-{hi:.1f}.")
    return "\n".join(lines)


def main() -> None:
    args = tyro.cli(StepBench)
    scene = PreparedScene.load(ensure_default_scene(args.cache, keyframes=6, progress=True))
    rows = []
    for threads in args.threads:
        for name in CASES:
            r = run_case(scene, name, threads, args)
            r["steps"] = args.steps
            print(r, flush=True)
            rows.append(r)
    result = {"rows": rows, "commit": git_commit(ROOT), "date": time.strftime("%Y-%m-%d"),
              "machine": {"cpus": os.cpu_count()}}
    publish(result, args.out, table(rows), args.docs, "step")


if __name__ == "__main__":
    main()
