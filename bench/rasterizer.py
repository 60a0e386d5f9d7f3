"""Benchmark of the differentiable rasterizer: compiled "cpu" backend vs the torch reference.

Usage: python bench/rasterizer.py [--reps 5] [--reference-reps 1] [--no-reference]
Writes bench/results/rasterizer.json and the table in docs/rasterizer.md (between markers).
Scenes: random Gaussians in the view frustum whose 3-sigma screen radius is log-uniform in
[2, 20] px (atgs.render.scenes.random_scene). Times are wall-clock medians.
"""

from __future__ import annotations

import os
import platform
import statistics
import sys
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import torch
import tyro
from tqdm import tqdm

from atgs.render import rasterize
from atgs.render.cpu import pair_counts
from atgs.render.scenes import random_scene
from _docs import update_docs_table, write_json_atomic  # bench/_docs.py (the script's own folder is on sys.path)

ROOT = Path(__file__).resolve().parents[1]


@dataclass
class BenchConfig:
    counts: tuple[int, ...] = (10_000, 100_000)
    sizes: tuple[tuple[int, int], ...] = ((256, 256), (640, 480))
    target: tuple[int, int, int] = (20_000, 256, 256)  # N, W, H of the target case
    reps: int = 5  # timed repetitions of the cpu backend (median reported), after 1 warm-up
    reference_reps: int = 1  # timed repetitions of the torch reference (slow)
    no_reference: bool = False  # skip the reference (then no speed-up is reported)
    seed: int = 0
    json_out: Path = ROOT / "bench" / "results" / "rasterizer.json"
    doc: Path = ROOT / "docs" / "rasterizer.md"
    cases: list[tuple[int, int, int]] = field(default_factory=list)  # filled from the above


def time_backend(backend: str, n: int, w: int, h: int, reps: int, seed: int) -> dict[str, float]:
    """Median forward and forward+backward wall times in ms (loss touches image, alpha, depth)."""
    scene = random_scene(n, w, h, seed=seed)
    fwd, fwd_bwd = [], []
    for rep in range(reps + (1 if backend == "cpu" else 0)):  # cpu: one untimed warm-up
        params = [t.clone().requires_grad_(True) for t in scene.gaussians()]
        with torch.no_grad():
            t0 = time.perf_counter()
            rasterize(*params, scene.viewmat, scene.K, w, h, backend=backend)
            t1 = time.perf_counter()
        t2 = time.perf_counter()
        out = rasterize(*params, scene.viewmat, scene.K, w, h, backend=backend)
        (out.image.sum() + out.alpha.sum() + out.depth.sum()).backward()
        t3 = time.perf_counter()
        if backend == "cpu" and rep == 0:
            continue
        fwd.append(1e3 * (t1 - t0))
        fwd_bwd.append(1e3 * (t3 - t2))
    return {"forward_ms": statistics.median(fwd), "forward_backward_ms": statistics.median(fwd_bwd), "reps": len(fwd)}


def cpu_time_one_thread(n: int, w: int, h: int, reps: int, seed: int) -> dict[str, float]:
    """Median process CPU time (ms) of the cpu backend on one thread: the work itself, which other
    jobs on a shared machine do not inflate the way they inflate wall-clock times."""
    scene = random_scene(n, w, h, seed=seed)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        fwd, total = [], []
        for rep in range(reps + 1):
            params = [t.clone().requires_grad_(True) for t in scene.gaussians()]
            c0 = time.process_time()
            out = rasterize(*params, scene.viewmat, scene.K, w, h, backend="cpu")
            c1 = time.process_time()
            (out.image.sum() + out.alpha.sum() + out.depth.sum()).backward()
            c2 = time.process_time()
            if rep:
                fwd.append(1e3 * (c1 - c0))
                total.append(1e3 * (c2 - c0))
    finally:
        torch.set_num_threads(threads)
    return {"forward_ms": statistics.median(fwd), "forward_backward_ms": statistics.median(total)}


def run(cfg: BenchConfig) -> dict:
    cases = [(n, w, h) for (w, h) in cfg.sizes for n in cfg.counts]
    if cfg.target not in cases:
        cases.insert(0, cfg.target)
    load_before = os.getloadavg()
    rows = []
    for n, w, h in tqdm(cases, desc="rasterizer bench", unit="case"):
        scene = random_scene(n, w, h, seed=cfg.seed)
        stats = pair_counts(scene.means, scene.quats, scene.scales, scene.opacities, scene.viewmat, scene.K, w, h)
        row: dict = {"n": n, "width": w, "height": h, **stats}
        row["cpu"] = time_backend("cpu", n, w, h, cfg.reps, cfg.seed)
        row["cpu"]["blended_pairs_per_s_forward"] = stats["blended_pairs"] / (row["cpu"]["forward_ms"] / 1e3)
        row["cpu_1thread_cpu_time_ms"] = cpu_time_one_thread(n, w, h, cfg.reps, cfg.seed)
        if not cfg.no_reference:
            row["torch"] = time_backend("torch", n, w, h, cfg.reference_reps, cfg.seed)
            row["speedup_forward"] = row["torch"]["forward_ms"] / row["cpu"]["forward_ms"]
            row["speedup_forward_backward"] = row["torch"]["forward_backward_ms"] / row["cpu"]["forward_backward_ms"]
        rows.append(row)
    result = {
        "benchmark": "rasterizer",
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": {
            "cpu": _cpu_model(), "cores": os.cpu_count(), "torch_threads": torch.get_num_threads(),
            "torch": torch.__version__, "python": platform.python_version(),
            "load_average_before": load_before, "load_average_after": os.getloadavg(),
        },  # fmt: skip
        "scene": "random_scene: frustum z in [2,10], 3-sigma radius log-uniform in [2,20] px, opacity U[0.05,1]",
        "target": {"n": cfg.target[0], "width": cfg.target[1], "height": cfg.target[2],
                   "forward_backward_ms_max": 50, "speedup_min": 30},  # fmt: skip
        "results": rows,
    }
    return result


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def table(result: dict) -> str:
    m = result["machine"]
    lines = [
        f"Measured {result['date']} on {m['cpu']} ({m['cores']} cores, torch {m['torch']}, "
        f"{m['torch_threads']} threads); load average before/after: "
        f"{m['load_average_before'][0]:.2f} / {m['load_average_after'][0]:.2f} "
        "(other jobs on the machine inflate the times).",
        "",
        "| N | image | visible | blended pairs | cpu fwd ms | cpu fwd+bwd ms | pairs/s (fwd) "
        "| cpu 1-thread CPU-time fwd / fwd+bwd ms "
        "| torch fwd ms | torch fwd+bwd ms | speed-up fwd | speed-up fwd+bwd |",
        "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in result["results"]:
        c, t = r["cpu"], r.get("torch")
        ref = (
            f"{t['forward_ms']:.0f} | {t['forward_backward_ms']:.0f} | {r['speedup_forward']:.0f}x | "
            f"{r['speedup_forward_backward']:.0f}x"
            if t
            else "- | - | - | -"
        )
        lines.append(
            f"| {r['n']:,} | {r['width']}x{r['height']} | {r['visible']:,} | {r['blended_pairs'] / 1e6:.1f}M | "
            f"{c['forward_ms']:.1f} | {c['forward_backward_ms']:.1f} | {c['blended_pairs_per_s_forward'] / 1e6:.0f}M | "
            f"{r['cpu_1thread_cpu_time_ms']['forward_ms']:.1f} / {r['cpu_1thread_cpu_time_ms']['forward_backward_ms']:.1f} | {ref} |"
        )
    return "\n".join(lines)


def main(cfg: BenchConfig) -> None:
    result = run(cfg)
    write_json_atomic(cfg.json_out, result)
    update_docs_table(cfg.doc, "rasterizer", table(result), create_section="Benchmark")
    print(table(result))
    print(f"wrote {cfg.json_out} and {cfg.doc}", file=sys.stderr)


if __name__ == "__main__":
    main(tyro.cli(BenchConfig))
