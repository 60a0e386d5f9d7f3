"""Anchor velocities from optical flow (atgs.train.scene_flow) on the built-in large-motion scene.

    python bench/velocity_init.py                       # both parts (~20 min on 2 cores)
    python bench/velocity_init.py --parts accuracy      # the estimates against the true motion only
    python bench/velocity_init.py --replot              # the tables again from the results file

- accuracy: the per-keyframe anchors' velocities that the trainer's set-up measures, against the
  true velocity of the nearest surface point of the synthetic scene's moving objects (anchors
  within 0.3 m of one), per object: median cosine, median length ratio, median relative error,
  and the set-up time (torch threads as given).
- training: preset `cpu` for a fixed step count (default 600), three runs at once with one torch
  thread each: velocities starting at 0 (`--train.no-velocity-from-flow`), from the flow (the
  default), and from the true motion (the oracle, the bound of what a better estimate could give).
  Held-out cam00 over all frames (the trainer's final evaluation) and the moving / static / seen
  split of bench/_splits.py. `--scene-dir DIR` runs this part on another prepared synthetic scene
  (e.g. `atgs-synth --layout front6`), `--cases zero flow` without the oracle.
- budget (not in the default parts): preset `cpu-fast` with its 5-minute budget, with and without
  the flow, two runs at once with one torch thread each: the set-up is paid from the budget, so
  this is the trade at equal time (`--parts budget`).

Results: bench/results/velocity_init.json and the bench:velocity-init table in docs/training.md.
"""

from __future__ import annotations

import json
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro
from _docs import publish, run_stamp  # bench/ (the script's own folder is on sys.path)
from _harness import build_trainer, run_timed, run_worker

from atgs.data.oracle import source_frame
from atgs.data.scene import PreparedScene
from atgs.data.synth.videos import ensure_default_scene, load_ground_truth
from atgs.io.cache import cache_dir
from atgs.train.scene_flow import grey_of, initial_velocities

ROOT = Path(__file__).resolve().parent.parent
CASES = {"zero": "velocities start at 0", "flow": "from optical flow (default)", "oracle": "from the true motion"}


@dataclass
class VelocityBench:
    parts: tuple[str, ...] = ("accuracy", "training")
    scene_dir: Path | None = None
    """training: another prepared synthetic scene (atgs-synth output prepared with atgs-prepare)
    instead of the built-in one; its rows are kept under its folder's name."""
    cases: tuple[str, ...] = tuple(CASES)  # training: which of zero, flow, oracle
    replot: bool = False  # the tables again from the results file, nothing run
    iterations: int = 600
    work_dir: Path = Path("/tmp/atgs-bench-velocity")
    out: Path = ROOT / "bench" / "results" / "velocity_init.json"
    docs: Path | None = ROOT / "docs" / "training.md"
    worker: str = ""  # internal: run one training case and print its JSON


def built_in() -> Path:
    return ensure_default_scene(cache_dir(), progress=False)


def _movers(gt) -> list:
    return [o for o in gt.objects if not o.static]


def _world_vertices(gt, obj, frame: float) -> np.ndarray:
    return gt.object_space_mesh(obj, frame).transformed(gt.model_matrix(obj, frame)).positions.astype(np.float64)


def true_velocities(model, scene: PreparedScene, gt, radius: float = 0.3) -> tuple[torch.Tensor, torch.Tensor]:
    """(A, 3) true velocity (world units per keyframe interval) of the nearest moving-object vertex
    of each per-keyframe anchor within ``radius``, 0 elsewhere, and (A,) the object's index (-1)."""
    tl = model.timeline
    per_interval = (tl.num_frames - 1) / max(1, tl.num_keyframes - 1)
    vel = torch.zeros(model.num_anchors, 3)
    label = torch.full((model.num_anchors,), -1)
    for k, f_prepared in enumerate(tl.keyframe_frames()):
        rows = (model.anchor_keyframe == k).nonzero().squeeze(1)
        if rows.numel() == 0:
            continue
        f = source_frame(scene, f_prepared)
        verts, vels, objs = [], [], []
        for oi, o in enumerate(_movers(gt)):
            p0 = _world_vertices(gt, o, f)
            verts.append(p0)
            vels.append(_world_vertices(gt, o, f + 0.5) - _world_vertices(gt, o, f - 0.5))
            objs.append(np.full(len(p0), oi))
        V = torch.tensor(np.concatenate(verts), dtype=torch.float32)
        dmin, j = torch.cdist(model.anchor_mu.index_select(0, rows), V).min(1)
        ok = dmin < radius
        vel[rows[ok]] = torch.tensor(np.concatenate(vels), dtype=torch.float32)[j[ok]] * per_interval
        label[rows[ok]] = torch.tensor(np.concatenate(objs))[j[ok]]
    return vel, label


def accuracy() -> dict:
    scene_dir = built_in()
    scene, gt = PreparedScene.load(scene_dir), load_ground_truth(scene_dir / "synth.json")
    tr = build_trainer(scene, Path("/tmp/atgs-bench-velocity/accuracy"), "cpu", iterations=100,
                       train={"velocity_from_flow": False})
    model = tr.model
    truth, label = true_velocities(model, scene, gt)
    cams = [scene.cameras[i] for i in tr.train_idx]
    t0 = time.perf_counter()
    est, stats = initial_velocities(model.anchor_mu, model.anchor_keyframe, model.voxel_size,
                                    model.timeline.keyframe_frames(), model.num_frames, cams,
                                    lambda ci, f: grey_of(scene.image_uint8(tr.train_idx[ci], f)))
    secs = time.perf_counter() - t0
    rows = {}
    for oi, o in enumerate(_movers(gt)):
        sel = label == oi
        if not bool(sel.any()):
            continue
        t, e = truth[sel], est[sel]
        mag = t.norm(dim=1).clamp_min(1e-9)
        rows[o.name] = {"anchors": int(sel.sum()), "true_speed": round(float(mag.median()), 3),
                        "cosine": round(float(torch.nn.functional.cosine_similarity(e, t, dim=1).median()), 3),
                        "ratio": round(float((e.norm(dim=1) / mag).median()), 3),
                        "rel_error": round(float(((e - t).norm(dim=1) / mag).median()), 3)}
    return {"objects": rows, "seconds": round(secs, 1), "threads": torch.get_num_threads(),
            "moving_anchors": int((model.anchor_keyframe >= 0).sum()), "stats": stats, **run_stamp(load=False)}


def train_case(case: str, iterations: int, work_dir: Path, scene_dir: Path | None = None) -> dict:
    from _splits import held_out_splits

    scene_dir = scene_dir or built_in()
    scene = PreparedScene.load(scene_dir)
    run = work_dir / f"run-{scene_dir.name}-{case}"
    tr = build_trainer(scene, run, "cpu", iterations=iterations, train={"velocity_from_flow": case == "flow"})
    if case == "oracle":
        vel, _ = true_velocities(tr.model, scene, load_ground_truth(scene_dir / "synth.json"))
        tr.model.anchor_velocity.copy_(vel)
    timed = run_timed(tr)
    ev = timed.eval
    return {"case": case, "what": CASES[case], "scene": scene_dir.name, "iterations": iterations,
            "train_s": round(timed.seconds, 1), "psnr": round(ev["psnr"], 2), "ssim": round(ev["ssim"], 4),
            "views": ev["views"], "split": held_out_splits(run / "ckpt.pt", scene_dir),
            "scene_flow": tr.scene_flow_stats, **run_stamp()}


def budget_case(case: str, minutes: float, work_dir: Path) -> dict:
    from _splits import held_out_splits

    scene_dir = built_in()
    scene = PreparedScene.load(scene_dir)
    run = work_dir / f"budget-{case}"
    t0 = time.perf_counter()  # the set-up (the flow) is paid from the budget: timed with the steps
    tr = build_trainer(scene, run, "cpu-fast", minutes=minutes, train={"velocity_from_flow": case == "flow"})
    ev = run_timed(tr).eval
    return {"case": case, "what": CASES[case], "preset": "cpu-fast", "minutes": minutes, "steps": tr.step,
            "wall_s": round(time.perf_counter() - t0, 1), "psnr": round(ev["psnr"], 2), "ssim": round(ev["ssim"], 4),
            "scene_flow": tr.scene_flow_stats, "split": held_out_splits(run / "ckpt.pt", scene_dir), **run_stamp()}


def table(result: dict) -> str:
    lines = []
    acc = result.get("accuracy")
    if acc:
        lines += ["| moving object | anchors | true speed | cosine | length ratio | relative error |",
                  "|---|---|---|---|---|---|"]
        for name, r in acc["objects"].items():
            lines.append(f"| {name} | {r['anchors']:,} | {r['true_speed']:.3f} | {r['cosine']:.3f} | {r['ratio']:.2f} | "
                         f"{r['rel_error']:.2f} |")
        lines += ["", f"Velocities of the per-keyframe anchors measured by the trainer's set-up against the true "
                  f"motion of the nearest surface point (anchors within 0.3 m of a moving object; medians; speeds in "
                  f"world units per keyframe interval). {acc['moving_anchors']:,} moving anchors, "
                  f"{acc['stats']['measured']:,} of {acc['stats']['tracked']:,} tracked anchors measured; set-up "
                  f"{acc['seconds']:.0f} s with {acc['threads']} torch thread{'s' if acc['threads'] != 1 else ''} "
                  f"({acc['date']}).", ""]
    for key in ["training"] + sorted(k for k in result if k.startswith("training@")):
        runs = result.get(key) or {}
        if not runs:
            continue
        where = key.split("@", 1)[1] if "@" in key else ""
        lines += [f"| velocities{f' ({where})' if where else ''} | steps | PSNR | SSIM | moving | static | seen | "
                  "change at window switches / other frames |", "|---|---|---|---|---|---|---|---|"]
        for r in (runs[c] for c in CASES if c in runs):
            s = r["split"]
            lines.append(f"| {r['what']} | {r['iterations']:,} | {r['psnr']:.2f} | {r['ssim']:.3f} | {s['psnr_moving']:.2f} | "
                         f"{s['psnr_static']:.2f} | {s['psnr_seen']:.2f} | {s['psnr_change_switch']:.2f} / "
                         f"{s['psnr_change_steady']:.2f} |")
        r = next(iter(runs.values()))
        if not where:
            lines += ["", f"Built-in large-motion scene, preset cpu at a fixed {r['iterations']:,} steps, three runs at "
                      f"once with one torch thread each ({r['date']}); held-out cam00 over all frames, the split every "
                      f"8th frame (bench/_splits.py). `python bench/velocity_init.py`.", ""]
        else:
            lines += ["", f"The same at a fixed {r['iterations']:,} steps on another layout, {r.get('layout', where)}, "
                      f"runs at once with one torch thread each ({r['date']}). `python bench/velocity_init.py --parts "
                      f"training --scene-dir DIR --cases zero flow --iterations {r['iterations']}`.", ""]
    budget = result.get("budget") or {}
    if budget:
        lines += ["| velocities | preset, budget | steps | PSNR | SSIM | moving | static | seen |", "|---|---|---|---|---|---|---|---|"]
        for case in ("zero", "flow"):
            r = budget.get(case)
            if r is None:
                continue
            s = r["split"]
            lines.append(f"| {r['what']} | {r['preset']}, {r['minutes']:g} min | {r['steps']:,} | {r['psnr']:.2f} | "
                         f"{r['ssim']:.3f} | {s['psnr_moving']:.2f} | {s['psnr_static']:.2f} | {s['psnr_seen']:.2f} |")
        r = next(iter(budget.values()))
        lines += ["", f"The built-in scene with preset cpu-fast's time budget, the set-up paid from it, two runs at once "
                  f"with one torch thread each ({r['date']}). `python bench/velocity_init.py --parts budget`."]
    return "\n".join(lines)


def main() -> None:
    args = tyro.cli(VelocityBench)
    if args.worker:
        case, _, kind = args.worker.partition(":")
        r = (budget_case(case, 5.0, args.work_dir) if kind == "budget"
             else train_case(case, args.iterations, args.work_dir, args.scene_dir))
        print(json.dumps(r), flush=True)
        return
    result = json.loads(args.out.read_text()) if args.out.exists() else {}
    if args.replot:
        publish(result, args.out, table(result), args.docs, "velocity-init")
        return
    built_in()  # prepared once, before any worker starts
    args.work_dir.mkdir(parents=True, exist_ok=True)
    if "accuracy" in args.parts:
        result["accuracy"] = accuracy()

    def one(worker: str) -> dict:
        cmd = [sys.executable, __file__, "--worker", worker, "--iterations", str(args.iterations),
               "--work-dir", str(args.work_dir)] + (["--scene-dir", str(args.scene_dir)] if args.scene_dir else [])
        return run_worker(cmd, args.work_dir / f"{worker.replace(':', '-')}.log")

    if "training" in args.parts:
        key = "training" if args.scene_dir is None else f"training@{args.scene_dir.name}"
        with ThreadPoolExecutor(len(args.cases)) as pool:
            result[key] = dict(zip(args.cases, pool.map(one, args.cases)))
    if "budget" in args.parts:
        pair = ("zero", "flow")
        with ThreadPoolExecutor(len(pair)) as pool:
            result["budget"] = dict(zip(pair, pool.map(one, [f"{c}:budget" for c in pair])))
    publish(result, args.out, table(result), args.docs, "velocity-init")


if __name__ == "__main__":
    main()
