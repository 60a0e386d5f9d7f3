"""Real capture, end to end: the N3DV flame_steak frame in ../shared/data, prepared with dense
stereo (the default) and with SIFT alone (`--no-stereo`), each trained with the default preset.

    python bench/n3dv.py                       # both preparations, both trainings (~25 min)
    python bench/n3dv.py --minutes 10          # a shorter time budget for both trainings

Prepare: `atgs-prepare SRC --downscale 4 --test-cams 0 --keyframes 1` (cam00 held out, the N3DV
convention). The two trainings run side by side with one torch thread each, so both see the
same machine. Reported per case: keyframe points, coverage of cam00 and of the training
cameras (scene.json), held-out PSNR/SSIM of cam00 as atgs-train prints it, steps and seconds.
Results: bench/results/n3dv.json and the bench:n3dv table in docs/data.md.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import tyro

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _docs import publish  # noqa: E402

from atgs.train.config import preset  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_SRC = ROOT.parent / "shared" / "data" / "n3dv_flame_steak_frame0"
CASES = {"stereo": [], "sift_only": ["--no-stereo"]}


@dataclass
class N3dvBench:
    src: Path = DEFAULT_SRC
    work_dir: Path = Path("/tmp/atgs-bench-n3dv")
    minutes: float | None = None
    """Time budget of each training (default: the preset's, 20 minutes for `cpu`)."""
    preset: str = "cpu"
    reuse_prepared: bool = False
    """Keep prepared scenes from an earlier run of this bench."""
    out: Path = ROOT / "bench" / "results" / "n3dv.json"
    docs: Path = ROOT / "docs" / "data.md"


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
    procs = {}
    load_before = list(os.getloadavg())
    for case, row in rows.items():
        run = args.work_dir / f"run-{case}"
        shutil.rmtree(run, ignore_errors=True)
        cmd = [*_cli("train"), "--data", row["scene"], "--out", str(run), "--preset", args.preset, "--train.threads", "1",
               "--no-progress"]
        if args.minutes is not None:
            cmd += ["--minutes", str(args.minutes)]
        procs[case] = (subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True), run)
    for case, (proc, run) in procs.items():
        stdout, _ = proc.communicate()
        print(stdout)
        if proc.returncode != 0:
            sys.exit(f"bench/n3dv.py: training {case} failed (exit {proc.returncode})")
        res = json.loads((run / "result.json").read_text())
        rows[case].update(psnr=res["eval"]["psnr"], ssim=res["eval"]["ssim"], eval_views=res["eval"]["views"],
                          steps=res["steps"], train_s=round(res["seconds"], 1))
    result = {"source": str(args.src), "downscale": 4, "test_camera": "cam00", "preset": args.preset,
              "minutes": args.minutes if args.minutes is not None else preset(args.preset)[1].minutes,
              "threads_per_run": 1, "runs_side_by_side": True, "cases": rows,
              "loadavg_before": load_before, "loadavg_after": list(os.getloadavg()),
              "cpus": os.cpu_count(), "date": time.strftime("%Y-%m-%d")}
    publish(result, args.out, table(result), args.docs, "n3dv")


def table(res: dict) -> str:
    lines = ["| keyframe points | points | cam00 coverage | training-camera coverage | held-out PSNR / SSIM (cam00) | "
             "steps | prepare s |", "|---|---|---|---|---|---|---|"]
    names = {"stereo": "stereo (default)", "sift_only": "SIFT alone (`--no-stereo`)"}
    for case, r in res["cases"].items():
        parts = " + ".join(f"{k} {v:,}" for k, v in r["points_by_source"].items() if v)
        secs = "-" if r["prepare_s"] is None else r["prepare_s"]  # None: prepared scene reused
        lines.append(f"| {names[case]} | {r['points']:,} ({parts}) | {r['coverage_cam00']:.0%} | "
                     f"{r['coverage_train_mean']:.0%} | {r['psnr']:.2f} dB / {r['ssim']:.3f} | {r['steps']:,} | {secs} |")
    lines.append("")
    lines.append(f"Preset `{res['preset']}`, budget {res['minutes']} (minutes), the two trainings side by side with one "
                 f"torch thread each on {res['cpus']} cores (load {res['loadavg_before'][0]:.1f} before, "
                 f"{res['loadavg_after'][0]:.1f} after); {res['date']}.")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
