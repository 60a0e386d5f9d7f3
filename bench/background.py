"""The background by direction (`--train.background-by-direction`) against one colour, at equal steps.

    python bench/background.py                                  # the built-in scene (~10 min on 2 cores)
    python bench/background.py --no-built-in --scene-dirs A B --iterations 400   # other prepared scenes
    python bench/background.py --no-built-in --scene-dirs A --labels "A, seed 1" --seed 1   # another seed
    python bench/background.py --replot                         # the table again from the results file

Per scene, preset `cpu` for a fixed step count, both cases at once with one torch thread each:
the background by direction (an environment map from the training images, the default) and the
images' mean colour (`--train.no-background-by-direction`, the default before 2026-11-26). Held-out
cameras over all frames (the trainer's final evaluation) and the split of bench/_splits.py
(moving / static; seen / unseen on atgs-synth scenes, where the unseen pixels are what the
background is for). Results: bench/results/background.json and the bench:background table in
docs/training.md.
"""

from __future__ import annotations

import json
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import tyro
from _docs import publish, run_stamp  # bench/ (the script's own folder is on sys.path)
from _harness import build_trainer, run_timed, run_worker

from atgs.data.scene import PreparedScene
from atgs.data.synth.videos import ensure_default_scene
from atgs.io.cache import cache_dir

ROOT = Path(__file__).resolve().parent.parent
CASES = {"direction": "by direction (default)", "colour": "the images' mean colour"}


@dataclass
class BackgroundBench:
    built_in: bool = True  # the built-in large-motion scene
    scene_dirs: tuple[Path, ...] = ()  # other prepared scenes
    labels: tuple[str, ...] = ()  # their names in the table (default: their folders' names)
    iterations: int = 1200
    seed: int = 0  # the trainer's seed (anchor sampling, view order)
    cases: tuple[str, ...] = tuple(CASES)  # which of direction, colour (the others' results are kept)
    replot: bool = False  # the table again from the results file, nothing run
    work_dir: Path = Path("/tmp/atgs-bench-background")
    out: Path = ROOT / "bench" / "results" / "background.json"
    docs: Path | None = ROOT / "docs" / "training.md"
    worker: str = ""  # internal: "CASE@SCENE_DIR", run one case and print its JSON


def train_case(case: str, scene_dir: Path, iterations: int, work_dir: Path, seed: int = 0) -> dict:
    from _splits import held_out_splits

    scene = PreparedScene.load(scene_dir)
    run = work_dir / f"run-{scene_dir.name}-{case}-s{seed}"  # as its log: one folder per scene, case and seed
    tr = build_trainer(scene, run, "cpu", iterations=iterations,
                       train={"background_by_direction": case == "direction", "seed": seed})
    timed = run_timed(tr)
    ev, cams = timed.eval, scene.cameras
    return {"case": case, "what": CASES[case], "scene": scene_dir.name, "iterations": iterations,
            "cameras": f"{len(scene.train_indices)} training + {len(scene.test_indices)} held out, "
                       f"{cams[0].width}x{cams[0].height}, {scene.num_frames} frame{'s' if scene.num_frames > 1 else ''}",
            "seed": seed, "train_s": round(timed.seconds, 1), "psnr": round(ev["psnr"], 2), "ssim": round(ev["ssim"], 4),
            "split": held_out_splits(run / "ckpt.pt", scene_dir), **run_stamp()}


def table(result: dict) -> str:
    lines = ["| scene | cameras | steps | background | PSNR | SSIM | static | moving | seen | unseen |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
    dates = set()
    for name, runs in result.items():
        for case in CASES:
            r = runs.get(case)
            if r is None:
                continue
            s = r["split"]
            dates.add(r["date"])
            lines.append(f"| {name} | {r['cameras']} | {r['iterations']:,} | {r['what']} | {r['psnr']:.2f} | "
                         f"{r['ssim']:.3f} | {fmt(s.get('psnr_static'))} | {fmt(s.get('psnr_moving'))} | "
                         f"{fmt(s.get('psnr_seen'))} | {fmt(s.get('psnr_unseen'))} |")
    lines += ["", f"Preset cpu at a fixed step count, the two cases of a scene at once with one torch thread each "
              f"({', '.join(sorted(dates))}); held-out cameras over all frames, the split every 8th frame "
              "(bench/_splits.py; seen / unseen only on atgs-synth scenes). `python bench/background.py`."]
    return "\n".join(lines)


def main() -> None:
    args = tyro.cli(BackgroundBench)
    if args.worker:
        case, _, scene_dir = args.worker.partition("@")
        print(json.dumps(train_case(case, Path(scene_dir), args.iterations, args.work_dir, args.seed)), flush=True)
        return
    result = json.loads(args.out.read_text()) if args.out.exists() else {}
    if args.replot:
        publish(result, args.out, table(result), args.docs, "background")
        return
    if args.labels and len(args.labels) != len(args.scene_dirs):
        raise SystemExit(f"--labels: {len(args.labels)} given for {len(args.scene_dirs)} --scene-dirs")
    scenes = ([("built-in", ensure_default_scene(cache_dir(), progress=False))] if args.built_in else []) + list(
        zip(args.labels or [d.name for d in args.scene_dirs], args.scene_dirs))
    args.work_dir.mkdir(parents=True, exist_ok=True)
    for label, scene_dir in scenes:
        PreparedScene.load(scene_dir)  # a bad path fails here, before any worker starts

        def one(case: str, scene_dir: Path = scene_dir) -> dict:
            cmd = [sys.executable, __file__, "--worker", f"{case}@{scene_dir}", "--iterations", str(args.iterations),
                   "--work-dir", str(args.work_dir), "--seed", str(args.seed)]
            return run_worker(cmd, args.work_dir / f"{scene_dir.name}-{case}-s{args.seed}.log")

        with ThreadPoolExecutor(len(args.cases)) as pool:
            result[label] = {**result.get(label, {}), **dict(zip(args.cases, pool.map(one, args.cases)))}
        publish(result, args.out, table(result), args.docs, "background")


if __name__ == "__main__":
    main()
