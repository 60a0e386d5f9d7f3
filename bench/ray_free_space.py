"""The per-ray free-space term on and off, on prepared captures, at equal machine share.

    python bench/ray_free_space.py --scenes builtin=/path/prepared dome=/tmp/dome-prep --minutes 5
    python bench/ray_free_space.py --scenes ... --weights 0 0.1 0.3      # more than two settings
    python bench/ray_free_space.py --replot

For each prepared scene, `atgs-train --train.lambda-ray-free-space W` runs once per weight W,
all the weights of a scene at the same time with one torch thread each (so every run of a row
sees the same machine), the default preset and a `--minutes` budget. Reported per run: steps,
the held-out PSNR/SSIM of atgs-train's final evaluation, the PSNR of each held-out camera
(eval/per_view.csv), and the training views' PSNR over the last tenth of the run
(train_log.csv): how far evaluation lags training. Results: bench/results/ray_free_space.json
(merged: a scene run again replaces its rows) and the bench:ray_free_space table in
docs/training.md.
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
import time
from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import tyro

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _docs import publish, run_stamp  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
RESULTS = ROOT / "bench" / "results" / "ray_free_space.json"


@dataclass
class RayFreeSpaceBench:
    scenes: list[str] = field(default_factory=list)
    """NAME=PREPARED_DIR pairs."""
    weights: list[float] = field(default_factory=lambda: [0.0, 0.1])
    """--train.lambda-ray-free-space values, run side by side per scene."""
    minutes: float = 5.0
    preset: str = "cpu"
    seed: int = 0
    work_dir: Path = Path("/tmp/atgs-bench-rayfs")
    extra: list[str] = field(default_factory=list)
    """Further atgs-train arguments for every run."""
    replot: bool = False


def per_camera(run: Path) -> dict[str, float]:
    """Mean PSNR per held-out camera from the final evaluation's per_view.csv."""
    path = run / "eval" / "per_view.csv"
    if not path.is_file():
        return {}
    by_cam: dict[str, list[float]] = defaultdict(list)
    with path.open() as f:
        for row in csv.DictReader(f):
            by_cam[row.get("camera") or row.get("cam")].append(float(row["psnr"]))
    return {c: round(sum(v) / len(v), 2) for c, v in sorted(by_cam.items())}


def training_psnr(run: Path) -> float | None:
    """Mean training-view PSNR over the last tenth of the logged steps (train_log.csv)."""
    path = run / "train_log.csv"
    if not path.is_file():
        return None
    with path.open() as f:
        vals = [float(r["psnr"]) for r in csv.DictReader(f) if r.get("psnr") not in (None, "", "nan")]
    if not vals:
        return None
    tail = vals[-max(1, len(vals) // 10):]
    return round(sum(tail) / len(tail), 2)


def train_one(name: str, scene: str, weight: float, args: RayFreeSpaceBench) -> dict:
    run = args.work_dir / f"{name}-w{weight:g}"
    cmd = [str(BIN / "atgs-train"), args.preset, "--data", scene, "--out", str(run), "--overwrite",
           "--train.minutes", str(args.minutes), "--train.threads", "1", "--train.seed", str(args.seed),
           "--train.lambda-ray-free-space", str(weight), "--no-progress", *args.extra]
    t0 = time.time()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        return {"scene": name, "weight": weight, "error": proc.stderr.strip().splitlines()[-1:]}
    res = json.loads((run / "result.json").read_text())
    ev = res.get("final_eval") or res.get("eval") or res
    return {"scene": name, "weight": weight, "steps": res.get("steps"), "wall_s": round(time.time() - t0, 1),
            "psnr": ev.get("psnr"), "ssim": ev.get("ssim"), "per_camera": per_camera(run),
            "train_psnr": training_psnr(run), "warnings": res.get("warnings", [])}


def table(rows: list[dict]) -> str:
    lines = ["| capture | weight | steps | held out PSNR | SSIM | per held-out camera | training views |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['scene']} | {r['weight']:g} | failed: {r['error']} | | | | |")
            continue
        cams = ", ".join(f"{c} {p:.1f}" for c, p in r["per_camera"].items())
        psnr = f"{r['psnr']:.2f} dB" if r.get("psnr") is not None else "-"
        ssim = f"{r['ssim']:.3f}" if r.get("ssim") is not None else "-"
        train = f"{r['train_psnr']:.1f} dB" if r.get("train_psnr") is not None else "-"
        lines.append(f"| {r['scene']} | {r['weight']:g} | {r['steps']} | {psnr} | {ssim} | {cams} | {train} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    args = tyro.cli(RayFreeSpaceBench, args=argv)
    old = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {"rows": []}
    rows = old["rows"]
    if not args.replot:
        args.work_dir.mkdir(parents=True, exist_ok=True)
        for pair in args.scenes:
            name, _, scene = pair.partition("=")
            with ThreadPoolExecutor(len(args.weights)) as pool:
                new = list(pool.map(lambda w: train_one(name, scene, w, args), args.weights))
            stamp = {**run_stamp(), "minutes": args.minutes, "preset": args.preset, "threads": 1}
            rows = [r for r in rows if r["scene"] != name] + [{**r, **stamp} for r in new]
            print(table([r for r in rows if r["scene"] == name]), flush=True)
    result = {"what": "held-out PSNR with the per-ray free-space term at each weight; runs of a capture side by "
                      "side, one torch thread each", "rows": rows}
    publish(result, RESULTS, table(rows), ROOT / "docs" / "training.md", "ray_free_space")


if __name__ == "__main__":
    main()
