"""What limits moving content (issue 11.5): the built-in large-motion scene trained from points on
the true surfaces, varying one factor at a time, PSNR measured separately on moving pixels.

    python bench/moving.py                                   # every case (~8 min each, 1 thread)
    python bench/moving.py --cases K6 K60 K6-W1              # some of them

Each case trains preset `cpu-fast` for a fixed step count (default 1,500) with one torch thread,
from oracle keyframe points (`sample_surface` of the synthetic scene's meshes at each keyframe,
4,000 per keyframe), so the geometry is right by construction and what remains is the model:
keyframe count K (anchors at the objects' positions at each keyframe), the window W, the
temporal segments M, the anchor layout, and model keyframes without points of their own.
Evaluation: cam00 and cam06 held out, every 8th frame; "moving" pixels differ from the camera's
temporal median by more than 0.08 (mean over RGB), about 8% of the pixels.
Results: bench/results/moving.json (merged by case) and the bench:moving table in docs/training.md.
"""

from __future__ import annotations

import json
import shutil
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
import tyro
from _docs import publish, run_stamp  # bench/ (the script's own folder is on sys.path)
from _harness import build_trainer, run_timed

from atgs.data.scene import MemoryScene, PreparedScene, write_prepared_scene
from atgs.data.synth.videos import ensure_default_scene, load_ground_truth
from atgs.data.synth.scene import sample_surface
from atgs.io.cache import cache_dir
from atgs.render import rasterize_gaussians
from atgs.timeline import evenly_spaced

ROOT = Path(__file__).resolve().parent.parent
# case name -> (keyframes with oracle points, model overrides)
CASES: dict[str, tuple[int, dict]] = {
    "K6": (6, {}),
    "K12": (12, {}),
    "K24": (24, {}),
    "K60": (60, {}),
    "K6-W1": (6, {"window": 1}),
    "K24-per-keyframe": (24, {"anchor_layout": "per-keyframe"}),
    "K24-M6": (24, {"num_segments": 6}),
    "K6-points-K48-model": (6, {"num_keyframes": 48}),
}


@dataclass
class MovingBench:
    cases: tuple[str, ...] = tuple(CASES)
    iterations: int = 1500
    points_per_keyframe: int = 4000
    work_dir: Path = Path("/tmp/atgs-bench-moving")
    cache: Path = field(default_factory=cache_dir)
    out: Path = ROOT / "bench" / "results" / "moving.json"
    docs: Path = ROOT / "docs" / "training.md"


def oracle_scene(base: Path, out: Path, keyframes: int, per_keyframe: int) -> Path:
    """A copy of the prepared built-in scene whose keyframes and points come from the meshes."""
    if (out / "scene.json").exists():
        return out
    src = PreparedScene.load(base)
    gt = load_ground_truth(base / "synth.json")
    kfs = evenly_spaced(src.num_frames, keyframes)
    pts, kf = [], []
    for j, f in enumerate(kfs):
        p = sample_surface(gt, f, per_keyframe, np.random.default_rng(j), max_radius=gt.cfg.wall_radius * 0.99)
        pts.append(p)
        kf.append(np.full(len(p), j))
    P = np.concatenate(pts)
    write_prepared_scene(out, MemoryScene(src.cameras, src.num_frames, src.fps, kfs, P, np.concatenate(kf),
                                          list(src.test_cameras), point_colors=np.full_like(P, 0.5)),
                         src.image_uint8, overwrite=True)
    shutil.copy2(base / "synth.json", out / "synth.json")
    return out


def moving_masks(scene, cams: list[int], frames: list[int]) -> dict:
    """Pixels that differ from the camera's temporal median (every 4th frame) by > 0.08."""
    masks = {}
    for ci in cams:
        med = np.median(np.stack([scene.image(ci, f) for f in range(0, scene.num_frames, 4)]), 0)
        for f in frames:
            masks[(ci, f)] = np.abs(scene.image(ci, f) - med).mean(-1) > 0.08
    return masks


def run_case(args: MovingBench, name: str, base: Path) -> dict:
    keyframes, overrides = CASES[name]
    scene_dir = oracle_scene(base, args.work_dir / f"oracle-K{keyframes}", keyframes, args.points_per_keyframe)
    scene = replace(PreparedScene.load(scene_dir), test_cameras=["cam00", "cam06"])
    tr = build_trainer(scene, args.work_dir / f"run-{name}", "cpu-fast", iterations=args.iterations, model=overrides)
    secs = run_timed(tr, "none").seconds
    frames = list(range(0, scene.num_frames, 8))
    masks = moving_masks(scene, tr.test_idx, frames)
    se = {"all": 0.0, "moving": 0.0}
    n = {"all": 0, "moving": 0}
    for ci in tr.test_idx:
        for f in frames:
            with torch.no_grad():
                img = rasterize_gaussians(tr.model.gaussians_at_frame(f), tr.cams[ci],
                                          near=tr.model.near).image.clamp(0, 1).numpy()
            err = ((img - scene.image(ci, f)) ** 2).mean(-1)
            mk = masks[(ci, f)]
            se["all"] += float(err.sum())
            n["all"] += err.size
            se["moving"] += float(err[mk].sum())
            n["moving"] += int(mk.sum())
    psnr = lambda s, c: float(-10 * np.log10(s / max(c, 1)))  # noqa: E731
    return {"case": name, "oracle_keyframes": keyframes, "model_overrides": overrides, "iterations": args.iterations,
            "model_keyframes": tr.model.num_keyframes, "segments": tr.model.num_segments,
            "anchors": tr.model.num_anchors, "train_s": round(secs, 1), "psnr": psnr(se["all"], n["all"]),
            "psnr_moving": psnr(se["moving"], n["moving"]),
            "psnr_static": psnr(se["all"] - se["moving"], n["all"] - n["moving"]),
            "moving_fraction": n["moving"] / n["all"], **run_stamp()}


def table(rows: dict) -> str:
    base = rows.get("K6")
    lines = ["| case | oracle keyframes | model K / M | anchors | PSNR all | PSNR moving pixels | PSNR static pixels | "
             "moving vs K6 |", "|---|---|---|---|---|---|---|---|"]
    for name in CASES:
        r = rows.get(name)
        if r is None:
            continue
        d = f"{r['psnr_moving'] - base['psnr_moving']:+.2f} dB" if base and name != "K6" else ""
        lines.append(f"| {name} | {r['oracle_keyframes']} | {r['model_keyframes']} / {r['segments']} | {r['anchors']:,} | "
                     f"{r['psnr']:.2f} | {r['psnr_moving']:.2f} | {r['psnr_static']:.2f} | {d} |")
    any_row = next(iter(rows.values()))
    lines.append("")
    lines.append(f"Preset cpu-fast, {any_row['iterations']:,} steps, 1 torch thread, oracle points "
                 f"({any_row['moving_fraction']:.1%} of the evaluated pixels move); cam00 and cam06 held out, every 8th frame.")
    return "\n".join(lines)


def main() -> None:
    args = tyro.cli(MovingBench)
    unknown = [c for c in args.cases if c not in CASES]
    if unknown:
        sys.exit(f"bench/moving.py: unknown case(s) {unknown}; choose from {list(CASES)}")
    torch.set_num_threads(1)
    base = ensure_default_scene(args.cache, keyframes=6, progress=True)
    rows = json.loads(args.out.read_text())["cases"] if args.out.exists() else {}
    for name in args.cases:
        print(f"[moving] {name} ...", flush=True)
        rows[name] = run_case(args, name, base)
        print(json.dumps(rows[name]), flush=True)
        publish({"cases": rows}, args.out, table(rows), args.docs, "moving")


if __name__ == "__main__":
    main()
