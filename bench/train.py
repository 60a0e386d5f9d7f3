"""Training benchmark: the built-in large-motion scene in a CPU preset, the paper's ablations
and peak memory for two sequence lengths.

    python bench/train.py                       # everything (long)
    python bench/train.py --only main           # just the main run
    python bench/train.py --only layout         # the main run with the paper's per-keyframe layout
    python bench/train.py --ablation-iterations 1500 --memory-frames 250 1000

Each configuration runs in its own subprocess so that its peak RSS is its own. Results go to
bench/results/train.json and a Markdown table to stdout (copied into docs/training.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import json
import os
from pathlib import Path
import sys
import time

import tyro

from atgs.io.cache import cache_dir
from atgs.io.atomic import write_json_atomic

ROOT = Path(__file__).resolve().parent.parent


@dataclass
class BenchArgs:
    preset: str = "cpu"
    iterations: int | None = None  # main run; default: the preset's
    ablation_iterations: int = 1500
    memory_iterations: int = 150
    memory_frames: tuple[int, ...] = (250, 1000)
    keyframes: int = 12  # keyframes of the prepared scene (the ablation "few" uses 3 of them)
    test_cameras: int = 2
    only: tuple[str, ...] = ("main", "ablations", "memory")
    """Parts to run; "layout" (not in the default) repeats the main run with the paper's
    per-keyframe anchor layout, stored with the ablations."""
    cache_dir: Path = field(default_factory=cache_dir)  # $ATGS_CACHE_DIR, else ~/.cache/atgs
    work_dir: Path = Path("/tmp/atgs-bench-train")
    out: Path = ROOT / "bench" / "results" / "train.json"
    threads: int = 0
    ablation_names: tuple[str, ...] = ()  # run only these ablations (merged by name into the results)


@dataclass
class RunSpec:
    name: str
    preset: str
    iterations: int | None
    scene_frames: int = 120
    scene_cameras: int = 12
    scene_width: int = 256
    scene_height: int = 192
    keyframes: int = 12
    test_cameras: int = 2
    model_overrides: dict = field(default_factory=dict)
    train_overrides: dict = field(default_factory=dict)
    threads: int = 0


def scene_for(spec: RunSpec, cache_dir: Path):
    from _harness import ring_scene

    return ring_scene(cache_dir, keyframes=spec.keyframes, test_cameras=spec.test_cameras, frames=spec.scene_frames,
                      cameras=spec.scene_cameras, width=spec.scene_width, height=spec.scene_height)


def run_one(spec: RunSpec, cache_dir: Path, work_dir: Path) -> dict:
    """Train one configuration in this process and return its measurements."""
    import resource

    import torch
    from _docs import utc_now
    from _harness import build_trainer, case_configs, run_timed

    if spec.threads:
        torch.set_num_threads(spec.threads)
    t_data = time.perf_counter()
    scene = scene_for(spec, cache_dir)
    t_data = time.perf_counter() - t_data
    trainer = build_trainer(scene, work_dir / spec.name, spec.preset, iterations=spec.iterations,
                            model=spec.model_overrides, train=spec.train_overrides, threads=spec.threads)
    res = run_timed(trainer, "renders", progress=sys.stderr.isatty()).result
    planned = case_configs(spec.preset, iterations=spec.iterations, train=spec.train_overrides)[1].iterations
    peak_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {"name": spec.name, "preset": spec.preset, "iterations": planned,
            "frames": scene.num_frames, "cameras": len(scene.cameras), "test_cameras": scene.test_cameras,
            "width": scene.cameras[0].width, "height": scene.cameras[0].height,
            "keyframes": trainer.model.num_keyframes, "segments": trainer.model.num_segments,
            "anchors": trainer.model.num_anchors, "train_seconds": res["seconds"],
            "scene_seconds": t_data, "psnr": res["eval"]["psnr"], "ssim": res["eval"]["ssim"],
            "eval_views": res["eval"]["views"], "peak_rss_mb": peak_kb / 1024.0,
            "model_overrides": spec.model_overrides, "torch_threads": torch.get_num_threads(),
            "date": utc_now(), "load_average": list(os.getloadavg())}  # 1, 5, 15 min at the end of the run


def run_subprocess(spec: RunSpec, args: BenchArgs) -> dict:
    from _harness import last_line, run_child

    cmd = [sys.executable, __file__, "--child", json.dumps(spec.__dict__), str(args.cache_dir), str(args.work_dir)]
    print(f"[bench] {spec.name}: {spec.preset}, {spec.iterations} it, {spec.scene_frames} frames, "
          f"{spec.model_overrides}", flush=True)
    r, stderr = run_child(cmd)
    if r is None:
        print(stderr[-3000:], file=sys.stderr)
        return {"name": spec.name, "error": last_line(stderr)}
    print(f"[bench]   PSNR {r['psnr']:.2f} SSIM {r['ssim']:.4f} train {r['train_seconds']:.0f}s "
          f"peak RSS {r['peak_rss_mb']:.0f} MB anchors {r['anchors']}", flush=True)
    return r


def table(rows: list[dict]) -> str:
    lines = ["| run | frames | K | M | iterations | anchors | PSNR | SSIM | train s | peak RSS MB |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['name']} | failed: {r['error']} |")
            continue
        lines.append(f"| {r['name']} | {r['frames']} | {r['keyframes']} | {r['segments']} | {r['iterations']} | "
                     f"{r['anchors']} | {r['psnr']:.2f} | {r['ssim']:.4f} | {r['train_seconds']:.0f} | "
                     f"{r['peak_rss_mb']:.0f} |")
    return "\n".join(lines)


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        spec = RunSpec(**json.loads(sys.argv[2]))
        print(json.dumps(run_one(spec, Path(sys.argv[3]), Path(sys.argv[4]))))
        return
    args = tyro.cli(BenchArgs)
    results: dict = {"machine": {"cpus": os.cpu_count()}}
    base = dict(keyframes=args.keyframes, test_cameras=args.test_cameras, threads=args.threads)

    def save() -> None:  # merge with what other bench processes wrote meanwhile
        args.out.parent.mkdir(parents=True, exist_ok=True)
        merged = json.loads(args.out.read_text()) if args.out.is_file() else {}
        for k, v in results.items():
            if k in ("ablations", "memory") and isinstance(merged.get(k), list):
                old = {r["name"]: r for r in merged[k]}
                old.update({r["name"]: r for r in v})
                merged[k] = list(old.values())
            elif k == "main":
                merged[k] = v
        merged.setdefault("machine", results["machine"])
        write_json_atomic(args.out, merged)

    if "main" in args.only:
        results["main"] = run_subprocess(RunSpec("main", args.preset, args.iterations, **base), args)
        save()
    if "layout" in args.only:
        spec = RunSpec("main schedule, per-keyframe anchor layout", args.preset, args.iterations,
                       model_overrides={"anchor_layout": "per-keyframe"}, **base)
        results["ablations"] = [run_subprocess(spec, args)]
        save()
    if "ablations" in args.only:
        it = args.ablation_iterations
        specs = [
            RunSpec("full (W=7, f_s, M=4, K=12)", args.preset, it, model_overrides={"num_segments": 4}, **base),
            RunSpec("no window (W=0)", args.preset, it, model_overrides={"num_segments": 4, "window": 0}, **base),
            RunSpec("without f_s", args.preset, it, model_overrides={"num_segments": 4, "use_spatial_grid": False},
                    **base),
            RunSpec("M=1", args.preset, it, model_overrides={"num_segments": 1}, **base),
            RunSpec("few keyframes (K=3)", args.preset, it, model_overrides={"num_segments": 4, "num_keyframes": 3},
                    **base),
        ]
        if args.ablation_names:
            specs = [s for s in specs if s.name in args.ablation_names]
        results["ablations"] = []
        for s in specs:
            results["ablations"].append(run_subprocess(s, args))
            save()
    if "memory" in args.only:
        mem = []
        for frames in args.memory_frames:
            spec = RunSpec(f"memory {frames} frames", args.preset, args.memory_iterations, scene_frames=frames,
                           scene_cameras=6, scene_width=128, scene_height=96, keyframes=args.keyframes,
                           test_cameras=1, threads=args.threads)
            mem.append(run_subprocess(spec, args))
            save()
        results["memory"] = mem
        save()
    results = json.loads(args.out.read_text())
    rows = ([results["main"]] if "main" in results else []) + results.get("ablations", []) + results.get("memory", [])
    print(table(rows))


if __name__ == "__main__":
    main()
