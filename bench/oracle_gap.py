"""Oracle gap: training from the stereo points against training from the true geometry.

For each synthetic layout of bench/stereo.py (atgs.data.synth.scene.LAYOUTS x motion preset) a
short clip is synthesized and prepared with the default prepare settings (dense stereo and the
fill on, cam00 held out; only the keyframe count is set), and its oracle copy is built
(atgs.data.oracle.make_oracle_scene: same frames, cameras, keyframes and bounds, points from the
true depth, capped like the stereo). Then `atgs-train` runs on both with the same preset and a
fixed step count (not a time budget), one torch thread each, the two runs of a case side by side
in two subprocesses so that both see the same machine load. The held-out PSNR / SSIM are
atgs-train's final evaluation (result.json: every frame of the test cameras, full resolution).
Target (issue 11): the stereo run within 1 dB of the oracle run on every layout.

Run by hand:  PYTHONPATH=. python bench/oracle_gap.py [--cases ring12/large-motion front6 ...]
              [--frames 30] [--keyframes 3] [--preset cpu-fast] [--iterations 800] [--no-write]
Writes bench/results/oracle_gap.json and the table in docs/data.md; scratch in --work-dir.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, replace
from datetime import datetime, timezone
from pathlib import Path

import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from atgs.data.oracle import make_oracle_scene  # noqa: E402
from atgs.data.prepare import PrepareConfig, prepare  # noqa: E402
from atgs.data.synth.videos import synthesize  # noqa: E402
from atgs.data.synth.scene import LAYOUTS, SynthConfig  # noqa: E402
from bench._docs import publish  # noqa: E402
from bench.stereo import CASES, load  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TARGET_DB = 1.0


@dataclass(frozen=True)
class GapBench:
    cases: tuple[str, ...] = ()
    """Cases to run, as LAYOUT/PRESET or LAYOUT (all its cases); default: all six."""
    frames: int = 30
    """Frames of each synthetic clip."""
    keyframes: int = 3
    """Keyframes of the prepared scene (points are reconstructed at each)."""
    preset: str = "cpu-fast"
    """atgs-train preset of both runs."""
    iterations: int = 800
    """Training steps of both runs (a fixed count, so both get the same steps)."""
    threads: int = 1
    """Torch threads of each training run."""
    work_dir: Path = Path("/tmp/gap")
    """Scratch: clips, prepared and oracle scenes, training runs and their logs."""
    no_write: bool = False
    """Print only; leave bench/results and docs alone."""


def select_cases(names: tuple[str, ...]) -> list[tuple[str, str]]:
    if not names:
        return list(CASES)
    chosen = []
    for n in names:
        layout, _, preset = n.partition("/")
        hits = [c for c in CASES if c[0] == layout and (not preset or c[1] == preset)]
        if not hits:
            raise SystemExit(f"--cases {n!r}: not a case; choose from "
                             + ", ".join(f"{layout}/{preset}" for layout, preset in CASES))
        chosen += [c for c in hits if c not in chosen]
    return chosen


def points_per_keyframe(scene: Path) -> list[int]:
    """All points of each keyframe (SIFT + stereo + fill, or the oracle's), from scene.json."""
    counts = json.loads((scene / "scene.json").read_text())["keyframe_points"]
    return [int(sum(c)) for c in zip(*counts.values())]


def coverage(scene: Path) -> dict:
    cov = json.loads((scene / "scene.json").read_text())["coverage"]
    return {"cam00": cov["test_cameras"].get("cam00"), "train_mean": cov["mean"]}


def train_side_by_side(runs: dict[str, tuple[Path, Path]], a: GapBench) -> dict[str, dict]:
    """atgs-train on each (data, out) at once; result.json, wall seconds and the load meanwhile."""
    env = dict(os.environ, OMP_NUM_THREADS=str(a.threads), PYTHONPATH=str(ROOT))
    procs, logs, ends = {}, {}, {}
    t0 = time.perf_counter()
    for name, (data, out) in runs.items():
        cmd = [sys.executable, "-m", "atgs.cli.train", a.preset, "--data", str(data), "--out", str(out),
               "--overwrite", "--train.iterations", str(a.iterations), "--train.threads", str(a.threads),
               "--no-progress"]
        logs[name] = open(out.parent / f"train-{name}.log", "w")
        procs[name] = subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=logs[name], stderr=subprocess.STDOUT)
    loads, next_sample = [load()], 15.0
    while len(ends) < len(procs):
        time.sleep(1.0)
        now = time.perf_counter() - t0
        for name, p in procs.items():
            if name not in ends and p.poll() is not None:
                ends[name] = now
        if now >= next_sample:
            loads.append(load())
            next_sample += 15.0
    res = {}
    for name, (_, out) in runs.items():
        logs[name].close()
        if procs[name].returncode != 0:
            tail = (out.parent / f"train-{name}.log").read_text().strip().splitlines()[-3:]
            raise RuntimeError(f"atgs-train on {runs[name][0]} failed ({procs[name].returncode}): " + " | ".join(tail))
        r = json.loads((out / "result.json").read_text())
        res[name] = {"psnr": round(r["eval"]["psnr"], 3), "ssim": round(r["eval"]["ssim"], 4), "steps": r["steps"],
                     "train_s": round(r["seconds"], 1), "wall_s": round(ends[name], 1), "anchors": r.get("anchors")}
    loads.append(load())
    for r in res.values():
        r["load"] = {"min": min(loads), "mean": round(sum(loads) / len(loads), 2), "max": max(loads)}
    return res


def run_case(layout: str, preset: str, a: GapBench) -> dict:
    work = a.work_dir / f"{layout}-{preset}"
    work.mkdir(parents=True, exist_ok=True)
    cfg = replace(SynthConfig(frames=a.frames, preset=preset), **LAYOUTS[layout])
    row: dict = {"layout": layout, "preset": preset, "cameras": cfg.cameras, "size": [cfg.width, cfg.height],
                 "date": datetime.now(timezone.utc).isoformat(timespec="seconds")}
    t = time.perf_counter()
    raw = synthesize(work / "raw", cfg, progress=False, overwrite=True)
    prepared = prepare(PrepareConfig(src=raw, out=work / "stereo", keyframes=a.keyframes, overwrite=True,
                                     progress=False))
    row["prepare_s"] = round(time.perf_counter() - t, 1)
    t = time.perf_counter()
    oracle = make_oracle_scene(prepared, work / "oracle", overwrite=True)
    row["oracle_s"] = round(time.perf_counter() - t, 1)
    for name, scene in (("stereo", prepared), ("oracle", oracle)):
        row[name] = {"points_per_keyframe": points_per_keyframe(scene), "coverage": coverage(scene)}
    trained = train_side_by_side({n: (s, work / f"run-{n}") for n, s in (("stereo", prepared), ("oracle", oracle))}, a)
    for name in ("stereo", "oracle"):
        row[name].update(trained[name])
    row["gap_db"] = round(row["oracle"]["psnr"] - row["stereo"]["psnr"], 3)
    row["within_target"] = row["gap_db"] <= TARGET_DB
    return row


def progress_line(i: int, n: int, row: dict, seconds: float) -> str:
    if "error" in row:
        return f"[{i}/{n}] {row['layout']} {row['preset']}: FAILED: {row['error']} ({seconds:.0f} s)"
    s, o = row["stereo"], row["oracle"]
    return (f"[{i}/{n}] {row['layout']} {row['preset']}: PSNR stereo {s['psnr']:.2f} / oracle {o['psnr']:.2f} dB, "
            f"gap {row['gap_db']:+.2f} dB, {s['steps']} steps in {s['train_s']:.0f} / {o['train_s']:.0f} s, "
            f"load {s['load']['mean']:.1f} ({seconds:.0f} s)")


def table(res: dict) -> str:
    st = res["settings"]
    lines = [f"{st['frames']} frames, {st['keyframes']} keyframes, cam00 held out; preset `{st['preset']}`, "
             f"{st['iterations']} steps, {st['threads']} torch thread per run, both runs of a case side by side "
             f"({res['cpus']} cores, shared).", "",
             "| layout | preset | cams | points/kf: stereo (oracle) | cam00 coverage: stereo (oracle) | "
             "PSNR dB: stereo / oracle | gap dB | SSIM: stereo / oracle | <= 1 dB | train s: stereo / oracle | "
             "load |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["cases"]:
        if "error" in r:
            lines.append(f"| {r['layout']} | {r['preset']} | {r.get('cameras', '-')} | failed: {r['error']} "
                         "| | | | | | | |")
            continue
        s, o = r["stereo"], r["oracle"]
        pts = lambda x: "/".join(f"{p:,}" for p in x["points_per_keyframe"])  # noqa: E731
        verdict = "yes" if r["within_target"] else f"no ({r['gap_db'] - TARGET_DB:.2f} over)"
        lines.append(f"| {r['layout']} | {r['preset']} | {r['cameras']} | {pts(s)} ({pts(o)}) | "
                     f"{s['coverage']['cam00']:.0%} ({o['coverage']['cam00']:.0%}) | {s['psnr']:.2f} / {o['psnr']:.2f} | "
                     f"{r['gap_db']:+.2f} | {s['ssim']:.3f} / {o['ssim']:.3f} | {verdict} | "
                     f"{s['train_s']:.0f} / {o['train_s']:.0f} | {s['load']['mean']:.1f} |")
    dates = sorted(r["date"][:10] for r in res["cases"] if "date" in r)
    if dates:
        lines.append(f"\nMeasured {dates[0]}" + (f" to {dates[-1]}" if dates[-1] != dates[0] else "")
                     + "; load: mean 1-minute load average during the two trainings.")
    return "\n".join(lines)


def main() -> None:
    a = tyro.cli(GapBench, description=__doc__)
    cases = select_cases(a.cases)
    res = {"machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
           "settings": {k: v for k, v in asdict(a).items() if k in ("frames", "keyframes", "preset", "iterations",
                                                                     "threads")},
           "target_db": TARGET_DB, "cases": []}
    for i, (layout, preset) in enumerate(cases, 1):
        t = time.perf_counter()
        try:
            row = run_case(layout, preset, a)
        except Exception as e:  # one failed case must not lose the others' results
            row = {"layout": layout, "preset": preset, "error": f"{type(e).__name__}: {e}"}
        res["cases"].append(row)
        print(progress_line(i, len(cases), row, time.perf_counter() - t), flush=True)
    if a.no_write:
        print(table(res))
        return
    publish(res, ROOT / "bench" / "results" / "oracle_gap.json", table(res), ROOT / "docs" / "data.md", "oracle-gap")


if __name__ == "__main__":
    main()
