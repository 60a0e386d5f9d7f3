"""The rigs people capture with, end to end: synthesize, prepare, train with the default preset
and its 20-minute budget, score the held-out cameras.

    python bench/rigs.py                                   # every case, one after another (~2.5 h on 2 cores)
    python bench/rigs.py --cases ring10-loose ring10-oracle
    python bench/rigs.py --minutes 2 --frames 30 --cases sparse4 --out /tmp/rigs.json   # a quick look
    python bench/rigs.py --replot                          # the table again from the results file
    python bench/rigs.py --cases --scenes "sleap4=/tmp/realrigs/sleap-minimal-prep"   # real captures, prepared
    python bench/rigs.py --cases dome27-stage --extra-train-args="--flag value" --tag=-flag   # an A/B row

Each case runs the commands a user would (`atgs-synth`, `atgs-prepare`, `atgs-train --train.minutes M`)
as subprocesses, alone on the machine (a time budget measures the machine), and keeps what
atgs-prepare reported (keyframe points, coverage, cameras per measured pixel, its warnings) and
what atgs-train reported (steps, held-out PSNR/SSIM: its final evaluation, atgs-eval's default;
its warnings). Cases (atgs/data/synth/scene.py LAYOUTS):

- `ring10-loose`, `ring10-true`: one ring of 10 inward-looking cameras whose poses_bounds.npy
  near/far are 10x too wide (`--bounds loose`), or the true ones;
- `ring10-oracle`: the loose ring started from the true geometry (atgs.data.oracle), everything
  else equal: what a perfect start would give;
- `dome24`: a capture-stage dome, 24 cameras on three rings that see each other, a walking
  person, cam00 and cam12 held out;
- `sparse4`: 4 cameras 90 degrees apart (3 training): what such a rig allows.
- `dome27-stage`: a dome as hard as a real capture stage (layout `dome-stage`): 27 cameras on
  three rings of 9 (heights 0.6, 1.7, 3.2 m; 4 m out, the top ring 3 m) that see each other's
  bodies, uniform light-grey walls and floor, lit evenly, with a faint texture (as faint as the
  CMU Panoptic dome's: where semi-transparent fog in front of a held-out camera costs the
  training views almost nothing), every camera its own exposure (gain within +-0.35 stops,
  offset within +-3.5 % of full scale; the held-out frames carry theirs), two people walking
  (1 m and 2.4 m circles, opposite ways) and the orbiting box, 320x180, near/far 10x too wide
  (`--bounds loose`); cam00, cam07 (low ring, 0 and 280 degrees), cam11 (middle, 93 degrees) and
  cam22 (top, 187 degrees) held out.

`--extra-train-args` passes flags on to every atgs-train run (one string, split as a shell
would: `--extra-train-args="--a 1 --b"`); `--tag` is appended to this run's case names, so that
an A/B keeps both rows (the row records the flags).

Real captures are prepared beforehand (bench/real_rigs.py converts public test data of other
projects; atgs-prepare) and given as `--scenes NAME=PREPARED_DIR`; the table names them by NAME.

Results: bench/results/rigs.json (merged: a case run again replaces its row) and the bench:rigs
table in docs/data.md; the README rows come from it (bench/readme_table.py).
"""

from __future__ import annotations

import json
import os
import platform
import shlex
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import tyro

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _docs import git_commit, publish  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent


@dataclass(frozen=True)
class Case:
    layout: str
    bounds: str = "true"
    oracle: bool = False
    test_cams: tuple[str, ...] = ()
    what: str = ""


CASES = {
    "ring10-loose": Case("ring10", "loose", what="10-camera ring, near/far 10x too wide"),
    "ring10-true": Case("ring10", "true", what="10-camera ring, true near/far"),
    "ring10-oracle": Case("ring10", "loose", oracle=True, what="10-camera ring, true-depth start (oracle)"),
    "dome24": Case("dome24", "true", test_cams=("cam00", "cam12"), what="24-camera dome, 3 rings, person"),
    "sparse4": Case("sparse4", "true", what="4 cameras 90 degrees apart (3 training)"),
    "dome27-stage": Case("dome-stage", "loose", test_cams=("cam00", "cam07", "cam11", "cam22"),
                         what="27-camera stage: grey walls, unequal exposure, 2 people, near/far 10x too wide"),
}


@dataclass
class RigsBench:
    cases: tuple[str, ...] = tuple(CASES)
    scenes: tuple[str, ...] = ()  # NAME=PREPARED_DIR: real captures, already prepared
    minutes: float = 20.0  # atgs-train's budget (the default preset's)
    frames: int = 120
    keyframes: int = 6
    preset: str = "cpu"
    threads: int = 0  # atgs-train's --train.threads (0: its default); 1 when two benches share the machine
    extra_train_args: str = ""  # more atgs-train flags, split as a shell would (an A/B of a loss, say)
    tag: str = ""  # appended to the case names of this run's rows (and run folders): an A/B keeps both
    replot: bool = False  # the table again from the results file, nothing run
    work_dir: Path = Path("/tmp/atgs-bench-rigs")
    out: Path = ROOT / "bench" / "results" / "rigs.json"
    docs: Path | None = ROOT / "docs" / "data.md"


def run(cmd: list[str], log: Path) -> str:
    """Run a command (stdout and stderr into ``log``); its stderr text, for the warnings."""
    t0 = time.perf_counter()
    with open(log, "w") as f:
        proc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[:2])} failed (exit {proc.returncode}); see {log}")
    print(f"  {Path(cmd[0]).name}: {time.perf_counter() - t0:.0f} s", flush=True)
    return log.read_text()


def warnings_in(text: str) -> list[str]:
    """The warning and note lines a command printed (``atgs-train: warning: ...`` as ``warning: ...``)."""
    lines = (line.split("\r")[-1].strip() for line in text.splitlines())
    lines = (line.split(": ", 1)[1] if line.startswith("atgs-") and ": warning:" in line else line for line in lines)
    return [line for line in lines if line.startswith("warning:") or line.startswith("note:")]


def prepared(case: Case, cfg: RigsBench) -> tuple[Path, list[str]]:
    """The case's prepared scene (made once per layout, bounds and frame count) and the warnings
    atgs-prepare printed."""
    tag = f"{case.layout}-{case.bounds}-f{cfg.frames}-k{cfg.keyframes}"
    raw, prep = cfg.work_dir / f"raw-{tag}", cfg.work_dir / f"prep-{tag}"
    log = cfg.work_dir / f"prepare-{tag}.log"
    if not (raw / "synth.json").is_file():
        run([str(BIN / "atgs-synth"), str(raw), "--layout", case.layout, "--bounds", case.bounds,
             "--frames", str(cfg.frames), "--overwrite"], cfg.work_dir / f"synth-{tag}.log")
    if not (prep / "scene.json").is_file():
        cmd = [str(BIN / "atgs-prepare"), str(raw), "--out", str(prep), "--keyframes", str(cfg.keyframes), "--overwrite"]
        if case.test_cams:
            cmd += ["--test-cams", *case.test_cams]
        run(cmd, log)
    said = warnings_in(log.read_text()) if log.is_file() else []
    if case.oracle:
        from atgs.data.oracle import make_oracle_scene

        oracle = cfg.work_dir / f"oracle-{tag}"
        if not (oracle / "scene.json").is_file():
            make_oracle_scene(prep, oracle)
        return oracle, said
    return prep, said


def train_command(scene_dir: Path, out: Path, cfg: RigsBench) -> list[str]:
    """atgs-train with the bench's budget and preset, then the extra flags (last: they win)."""
    cmd = [str(BIN / "atgs-train"), cfg.preset, "--data", str(scene_dir), "--out", str(out),
           "--train.minutes", str(cfg.minutes)] + (["--train.threads", str(cfg.threads)] if cfg.threads else [])
    return cmd + shlex.split(cfg.extra_train_args)


def training_view_figure(out: Path, scene: dict, cfg: RigsBench) -> dict | None:
    """atgs-eval of up to 4 evenly spread training cameras, every 10th frame: the training views'
    PSNR beside the held-out figure (the lag the periodic evaluation warns about). Both sides are
    also given exposure-matched (docs/evaluation.md), since held-out cameras have no learned
    exposure."""
    test = set(scene["test_cameras"])
    train = [c["name"] for c in scene["cameras"] if c["name"] not in test]
    if not train:
        return None
    pick = [train[round(k * (len(train) - 1) / 3)] for k in range(4)] if len(train) > 4 else train
    ev = out / "eval-training-views"
    run([str(BIN / "atgs-eval"), str(out / "ckpt.pt"), "--out", str(ev), "--cameras", *dict.fromkeys(pick),
         "--every", "10", "--images-per-camera", "0", "--no-lpips"], out / "eval-training-views.log")
    mean = json.loads((ev / "summary.json").read_text())["mean"]
    return {"cameras": list(dict.fromkeys(pick)), "psnr": round(mean["psnr"], 2),
            "psnr_matched": round(mean["psnr_matched"], 2)}


def held_out_figures(out: Path) -> dict:
    """The final evaluation's per-camera PSNR and exposure-matched PSNR (out/eval/summary.json)."""
    summary = json.loads((out / "eval" / "summary.json").read_text())
    return {"psnr_matched": round(summary["mean"]["psnr_matched"], 2),
            "per_camera": {c: {"psnr": round(m["psnr"], 2), "psnr_matched": round(m["psnr_matched"], 2)}
                           for c, m in summary["per_camera"].items()}}


def run_case(name: str, cfg: RigsBench, scene_dir: Path | None = None) -> dict:
    """One synthetic case of CASES, or (``scene_dir``) a prepared real capture; its row is named
    ``name`` + ``cfg.tag``."""
    case = CASES[name] if scene_dir is None else Case("real", "", what=f"real capture ({scene_dir.name})")
    print(f"{name}: {case.what}", flush=True)
    if scene_dir is None:
        scene_dir, prepare_said = prepared(case, cfg)
    else:
        prepare_said = []
    scene = json.loads((scene_dir / "scene.json").read_text())
    row = name + cfg.tag
    out = cfg.work_dir / f"run-{row}"
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    text = run(train_command(scene_dir, out, cfg), cfg.work_dir / f"train-{row}.log")
    wall = time.perf_counter() - t0
    res = json.loads((out / "result.json").read_text())
    held_out = held_out_figures(out) if res["eval"].get("on_test_cameras", True) else {}
    training_views = training_view_figure(out, scene, cfg)
    cams = scene["cameras"]
    cov = scene.get("coverage", {})
    return {
        "case": row, "what": case.what, "train_args": cfg.extra_train_args, "layout": case.layout,
        "bounds": case.bounds, "oracle": case.oracle,
        "cameras": f"{len(cams) - len(scene['test_cameras'])} training + {len(scene['test_cameras'])} held out, "
                   f"{cams[0]['width']}x{cams[0]['height']}, {scene['num_frames']} frames",
        "keyframe_points": scene.get("keyframe_points"), "coverage_mean": cov.get("mean"),
        "coverage_test": cov.get("test_cameras"), "views_per_pixel": cov.get("views_per_pixel", {}).get("mean"),
        "prepare_warnings": prepare_said, "minutes": cfg.minutes, "preset": cfg.preset, "threads": cfg.threads,
        "steps": res.get("steps"), "train_wall_s": round(wall, 1),
        "psnr": round(res["eval"]["psnr"], 2), "ssim": round(res["eval"]["ssim"], 4),
        "on_test_cameras": res["eval"].get("on_test_cameras", True), **held_out,
        "training_views": training_views,
        "train_warnings": res.get("warnings", []) + [w for w in warnings_in(text) if w not in res.get("warnings", [])],
        "date": time.strftime("%Y-%m-%d %H:%M"), "load_1min_at_end": round(os.getloadavg()[0], 2),
        "commit": git_commit(ROOT), "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
    }


def matched(r: dict) -> str:
    """'23.44 dB (22.3, 23.5, ...) / 26.50 dB' (rows of before psnr_matched: 'n/a')."""
    if "psnr_matched" not in r:
        return "n/a"
    cams = ", ".join(f"{m['psnr_matched']:.1f}" for m in r["per_camera"].values())
    tv = r.get("training_views")
    return f"{r['psnr_matched']:.2f} dB ({cams})" + (f" / {tv['psnr_matched']:.2f} dB" if tv else "")


def table(rows: list[dict]) -> str:
    head = ("| case | cameras | keyframe points (mean: SIFT + stereo + fill) | coverage (training) | "
            "cameras per measured pixel | steps in budget | held out PSNR / SSIM | exposure-matched: held out "
            "(per camera) / training views | what the commands said |\n"
            "|---|---|---|---|---|---|---|---|---|")
    out = [head]
    for r in rows:
        kp = r.get("keyframe_points") or {}
        mean = {k: round(sum(v) / len(v)) if v else 0 for k, v in kp.items()}
        said = "; ".join(w[:110] + ("..." if len(w) > 110 else "")
                         for w in dict.fromkeys(r["prepare_warnings"] + r["train_warnings"]))  # each once
        vpp = r.get("views_per_pixel")
        case = f"{r['case']}: {r['what']}" + (f" (`{r['train_args']}`)" if r.get("train_args") else "")
        out.append(f"| {case} | {r['cameras']} | {mean.get('sift', 0)} + {mean.get('stereo', 0)} + "
                   f"{mean.get('fill', 0)} | {100 * (r['coverage_mean'] or 0):.0f} % | "
                   f"{'n/a' if vpp is None else f'{vpp:.1f}'} | {r['steps']} ({r['minutes']:g} min) | "
                   f"**{r['psnr']:.2f} dB** / {r['ssim']:.3f} | {matched(r)} | {said or 'nothing'} |")
    return "\n".join(out)


def main() -> None:
    cfg = tyro.cli(RigsBench, description=__doc__)
    old = json.loads(cfg.out.read_text()) if cfg.out.is_file() else {"rows": []}
    rows = {r["case"]: r for r in old["rows"]}
    if not cfg.replot:
        unknown = [c for c in cfg.cases if c not in CASES]
        if unknown:
            raise SystemExit(f"unknown case {unknown[0]!r}; choose from {', '.join(CASES)}")
        cfg.work_dir.mkdir(parents=True, exist_ok=True)
        real = dict(s.split("=", 1) for s in cfg.scenes)
        for name in list(cfg.cases) + list(real):
            rows[name + cfg.tag] = run_case(name, cfg, Path(real[name]) if name in real else None)
            ordered = [rows[c] for c in CASES if c in rows] + [r for c, r in rows.items() if c not in CASES]
            publish({**old, "rows": ordered}, cfg.out, table(ordered), cfg.docs, "rigs")  # after each case: hours of work
    ordered = [rows[c] for c in CASES if c in rows] + [r for c, r in rows.items() if c not in CASES]
    publish({**old, "rows": ordered}, cfg.out, table(ordered), cfg.docs, "rigs")  # keeps the file's note


if __name__ == "__main__":
    main()
