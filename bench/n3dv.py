"""Real capture, end to end: the N3DV flame_steak frame in ../shared/data, prepared with dense
stereo (the default) and with SIFT alone (`--no-stereo`), each trained with the default preset.

    python bench/n3dv.py                       # both preparations, both trainings (~25 min)
    python bench/n3dv.py --minutes 10          # a shorter time budget for both trainings
    python bench/n3dv.py --seeds 0 1           # two seeds per case (~50 min): one frame and one
                                               # held-out view move by ~1.5 dB with the seed
    python bench/n3dv.py --seeds 4 5 --add-seeds   # two more seeds, kept with those in the results

Prepare: `atgs-prepare SRC --downscale 4 --test-cams 0 --keyframes 1` (cam00 held out, the N3DV
convention). The trainings run two at a time with one torch thread each, so every run sees the
same machine. Reported per case: keyframe points, coverage of cam00 and of the training
cameras (scene.json), held-out PSNR/SSIM of cam00 as atgs-train prints it per seed and their
mean, steps and seconds, and the held-out PSNR of the periodic evaluations against training
time (docs/images/n3dv_curve.png). Results: bench/results/n3dv.json and the bench:n3dv table in
docs/data.md.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _docs import publish  # noqa: E402

from atgs.io.atomic import atomic_file  # noqa: E402
from atgs.train.config import preset  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_SRC = ROOT.parent / "shared" / "data" / "n3dv_flame_steak_frame0"
CASES = {"stereo": [], "sift_only": ["--no-stereo"]}
NAMES = {"stereo": "stereo (default)", "sift_only": "SIFT alone (`--no-stereo`)"}


@dataclass
class N3dvBench:
    src: Path = DEFAULT_SRC
    work_dir: Path = Path("/tmp/atgs-bench-n3dv")
    minutes: float | None = None
    """Time budget of each training (default: the preset's, 20 minutes for `cpu`)."""
    preset: str = "cpu"
    reuse_prepared: bool = False
    """Keep prepared scenes from an earlier run of this bench."""
    seeds: tuple[int, ...] = (0,)
    """Training seeds per case (`--train.seed`); the table reports each and their mean."""
    jobs: int = 2
    """Trainings at a time (one torch thread each)."""
    reuse_runs: bool = False
    """Keep the finished trainings of an earlier run of this bench (same work dir) and train only
    the missing seeds: `--seeds 0 1 2 3 --reuse-runs` after `--seeds 0 1` adds two."""
    add_seeds: bool = False
    """Add this call's seeds to the runs already in `--out` (same source, preset, budget and
    keyframe points) instead of replacing them: `--seeds 4 5 6 7 --add-seeds` after a run of
    seeds 0-3 reports all eight, without the earlier runs' folders."""
    out: Path = ROOT / "bench" / "results" / "n3dv.json"
    docs: Path = ROOT / "docs" / "data.md"
    plot: Path = ROOT / "docs" / "images" / "n3dv_curve.png"


def _cli(name: str) -> list[str]:
    return [sys.executable, "-m", f"atgs.cli.{name}"]


def prepare(args: N3dvBench, case: str) -> tuple[Path, float | None]:
    out = args.work_dir / f"prepared-{case}"
    if args.reuse_prepared and (out / "scene.json").exists():
        return out, None  # not measured
    t = time.perf_counter()
    subprocess.run([*_cli("prepare"), str(args.src), "--out", str(out), "--downscale", "4", "--test-cams", "0",
                    "--keyframes", "1", "--overwrite", *CASES[case]], check=True)
    return out, time.perf_counter() - t


def main() -> None:
    args = tyro.cli(N3dvBench)
    if not args.src.is_dir():
        sys.exit(f"bench/n3dv.py: {args.src} not found; pass --src with the N3DV frame folder")
    args.work_dir.mkdir(parents=True, exist_ok=True)
    rows: dict[str, dict] = {}
    for case in CASES:
        scene, secs = prepare(args, case)
        meta = json.loads((scene / "scene.json").read_text())
        counts = meta["keyframe_points"]  # per source: {"sift": [...], "stereo": [...], "fill": [...]}
        rows[case] = {"prepare_s": None if secs is None else round(secs, 1), "points": int(sum(sum(v) for v in counts.values())),
                      "points_by_source": {k: int(sum(v)) for k, v in counts.items()},
                      "coverage_cam00": meta["coverage"]["test_cameras"]["cam00"],
                      "coverage_train_mean": meta["coverage"]["mean"], "scene": str(scene)}
    load_before = list(os.getloadavg())

    def train(case: str, seed: int) -> dict:
        run = args.work_dir / f"run-{case}-s{seed}"
        if args.reuse_runs and (run / "result.json").exists():
            return {**summarize(run, seed), "points": rows[case]["points"]}
        shutil.rmtree(run, ignore_errors=True)
        cmd = [*_cli("train"), args.preset, "--data", rows[case]["scene"], "--out", str(run),
               "--train.threads", "1", "--train.seed", str(seed), "--no-progress"]
        if args.minutes is not None:
            cmd += ["--train.minutes", str(args.minutes)]
        proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True)
        print(proc.stdout)
        if proc.returncode != 0:
            sys.exit(f"bench/n3dv.py: training {case} seed {seed} failed (exit {proc.returncode})")
        return {**summarize(run, seed), "points": rows[case]["points"]}  # the preparation it trained on

    earlier = earlier_runs(args, rows) if args.add_seeds else {}
    jobs = [(case, seed) for seed in args.seeds for case in rows]  # a seed's cases train side by side
    with ThreadPoolExecutor(max(1, args.jobs)) as pool:
        done = list(pool.map(lambda cs: train(*cs), jobs))
    for case in rows:
        rows[case]["runs"] = list(earlier.get(case, []))
    for (case, _), run in zip(jobs, done):
        rows[case]["runs"].append(run)
    for row in rows.values():
        row["runs"].sort(key=lambda r: r["seed"])
    seeds = sorted({r["seed"] for row in rows.values() for r in row["runs"]})
    for row in rows.values():
        runs = row["runs"]
        row.update(psnr=float(np.mean([r["psnr"] for r in runs])), ssim=float(np.mean([r["ssim"] for r in runs])),
                   steps=int(np.mean([r["steps"] for r in runs])), eval_views=runs[0]["eval_views"])
    result = {"source": str(args.src), "downscale": 4, "test_camera": "cam00", "preset": args.preset,
              "minutes": args.minutes if args.minutes is not None else preset(args.preset)[1].minutes,
              "threads_per_run": 1, "runs_at_a_time": args.jobs, "seeds": seeds,
              "cases": rows,
              "loadavg_before": load_before, "loadavg_after": list(os.getloadavg()),
              "cpus": os.cpu_count(), "date": time.strftime("%Y-%m-%d")}
    publish(result, args.out, table(result), args.docs, "n3dv")
    plot(result, args.plot)


def earlier_runs(args: N3dvBench, rows: dict[str, dict]) -> dict[str, list[dict]]:
    """Runs in `args.out` of the seeds this call does not train, refused unless they were measured
    on the same preparation and budget (a merged mean must average like with like)."""
    if not args.out.exists():
        sys.exit(f"bench/n3dv.py: --add-seeds needs earlier results in {args.out}; run without it first")
    old = json.loads(args.out.read_text())
    minutes = args.minutes if args.minutes is not None else preset(args.preset)[1].minutes
    # A preparation is not bit for bit repeatable (pycolmap's threaded SIFT matching and RANSAC):
    # two of the same frame differ by ~1 % of their points, which is kept apart from a changed one.
    same = (old["source"] == str(args.src) and old["preset"] == args.preset and old["minutes"] == minutes
            and all(c in old["cases"] and abs(old["cases"][c]["points"] - rows[c]["points"]) <= 0.02 * rows[c]["points"]
                    for c in rows))
    if not same:
        sys.exit(f"bench/n3dv.py: {args.out} was measured with another source, preset, budget or preparation; "
                 "rerun all seeds without --add-seeds")
    for c in rows:  # a reused preparation was not timed: keep the earlier timing
        if rows[c]["prepare_s"] is None:
            rows[c]["prepare_s"] = old["cases"][c]["prepare_s"]
    return {c: [r for r in old["cases"][c]["runs"] if r["seed"] not in args.seeds] for c in rows}


def summarize(run: Path, seed: int) -> dict:
    """One training's row: its final evaluation, steps, seconds and evaluation curve."""
    res = json.loads((run / "result.json").read_text())
    curve = eval_curve(run / "train_log.csv")
    if not curve or curve[-1][1] != res["steps"]:  # the final evaluation, when no periodic one fell on the last step
        curve.append((round(res["seconds"], 1), res["steps"], res["eval"]["psnr"]))
    return {"seed": seed, "psnr": res["eval"]["psnr"], "ssim": res["eval"]["ssim"], "eval_views": res["eval"]["views"],
            "steps": res["steps"], "train_s": round(res["seconds"], 1), "curve": curve}


def eval_curve(log: Path) -> list[tuple[float, int, float]]:
    """(seconds, step, held-out PSNR) of each periodic and the final evaluation in a train log."""
    with open(log) as fh:
        return [(float(r["seconds"]), int(r["step"]), float(r["eval_psnr"])) for r in csv.DictReader(fh) if r["eval_psnr"]]


def plot(res: dict, path: Path) -> None:
    """Held-out PSNR of the periodic evaluations against training minutes, one line per run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for case, color in zip(res["cases"], ("tab:blue", "tab:orange")):
        runs = res["cases"][case]["runs"]
        for i, run in enumerate(runs):  # one line per seed, one legend entry per case
            t, _, p = zip(*run["curve"]) if run["curve"] else ((), (), ())
            ax.plot([x / 60 for x in t], p, marker="o", markersize=3, color=color, alpha=0.7, linewidth=1,
                    label=f"{NAMES[case].replace('`', '')}, {len(runs)} seeds" if i == 0 else None)
    ax.set_xlabel("training minutes (1 torch thread, two runs at a time on 2 cores)")
    ax.set_ylabel("held-out PSNR, cam00 [dB]")
    ax.set_title(f"N3DV flame_steak frame 0, preset {res['preset']} ({res['date']})")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110)
    print(f"wrote {path}")


def _at_half(run: dict) -> str:
    """Held-out PSNR of the last evaluation up to half the run's training time."""
    half = [p for t, _, p in run["curve"] if t <= run["train_s"] / 2]
    return f"{half[-1]:.2f}" if half else "-"


def table(res: dict) -> str:
    lines = ["| keyframe points | points | cam00 coverage | training-camera coverage | held-out PSNR / SSIM (cam00), "
             "mean | PSNR per seed | PSNR at half the budget, per seed | steps | prepare s |",
             "|---|---|---|---|---|---|---|---|---|"]
    for case, r in res["cases"].items():
        parts = " + ".join(f"{k} {v:,}" for k, v in r["points_by_source"].items() if v)
        secs = "-" if r["prepare_s"] is None else r["prepare_s"]  # None: prepared scene reused
        per_seed = " / ".join(f"{x['psnr']:.2f}" for x in r["runs"])
        half = " / ".join(_at_half(x) for x in r["runs"])
        lines.append(f"| {NAMES[case]} | {r['points']:,} ({parts}) | {r['coverage_cam00']:.0%} | "
                     f"{r['coverage_train_mean']:.0%} | {r['psnr']:.2f} dB / {r['ssim']:.3f} | {per_seed} | {half} | "
                     f"{r['steps']:,} | {secs} |")
    lines.append("")
    lines.append(f"Preset `{res['preset']}`, budget {res['minutes']} (minutes), seeds {', '.join(map(str, res['seeds']))}"
                 f"; {res['runs_at_a_time']} trainings at a time with one torch thread each on {res['cpus']} cores "
                 f"(load {res['loadavg_before'][0]:.1f} before, {res['loadavg_after'][0]:.1f} after); {res['date']}. "
                 "Held-out PSNR against training time: docs/images/n3dv_curve.png.")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
