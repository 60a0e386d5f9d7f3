"""Knobs of the default run at a fixed time budget, on the built-in large-motion scene.

    python bench/budget_knobs.py                       # every case, two at a time, 1 torch thread each
    python bench/budget_knobs.py --cases w3 w7 --minutes 8

Each case trains preset `cpu` on the built-in scene (as `atgs-train` with no arguments prepares
it: dense stereo, the extension, motion points at 21 keyframes) for `--minutes` of wall time,
changing one or two knobs, and evaluates the held-out camera over every frame (the figure
`atgs-train` prints) and split by pixel (`bench/_splits.py`): moving / static, and *seen* (the
surface is visible in at least one training camera) / *unseen*. A knob that makes steps cheaper
buys more of them: the comparison is at equal time, not at equal steps.
Results: bench/results/budget_knobs.json (merged by case) and the bench:budget-knobs table in
docs/training.md.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
import json
from pathlib import Path
import shutil
import sys

import tyro

from _docs import publish, run_stamp  # bench/ (the script's own folder is on sys.path)
from _harness import build_trainer, run_timed, run_worker
from atgs.train.config import preset

ROOT = Path(__file__).resolve().parent.parent

# The paper's decode (no anchor motion), for the cases measured before motion became the default.
NO_MOTION = {"temporal_fade": False, "anchor_velocity": False}
# Random anchors were uniform in the box (not carved) when the cases up to the smoothing filter
# were measured; they keep that setting so that a rerun measures what their row says.
NO_CARVE = {"carve_random_anchors": False}
MOTION = {"window": 7, "temporal_fade": True, "anchor_velocity": True}
# The paper's volume loss, the CPU presets' until 2026-11-25 (the cases before w7-motion-volume).
SUM_VOLUME = {"volume_reduction": "sum", "lambda_volume": 0.001}
MEAN_VOXEL_VOLUME = {"volume_reduction": "mean-voxel", "lambda_volume": 0.01}
MEAN_BG = {"background_from_images": True, **SUM_VOLUME}

# case -> (description, model overrides, train overrides)
# The cpu preset's decode and losses since 2026-11-25 (case w7-motion-offset), the base of the later cases.
CARVED_MOTION = {**MOTION, "carve_random_anchors": True}
CPU_TRAIN = {**MEAN_BG, **MEAN_VOXEL_VOLUME, "lambda_offset": 0.01, "offset_free": 1.0}
# every anchor's feature and scale learning rate x3 (the paper's 0.0075 and 0.007)
ANCHOR_LR3 = {"anchor_feature": 0.0225, "anchor_scaling": 0.021}

SIZE_FIELDS = ("feature_dim", "gaussians_per_anchor", "spatial_resolution", "hidden_opacity", "hidden_cov",
               "hidden_color", "hidden_offset")
HASH_SIZE_FIELDS = ("levels", "features_per_level", "log2_table_size", "max_time_resolution", "mlp_hidden")


def model_sizes(preset_name: str) -> dict:
    """The model sizes of a preset (features, Gaussians per anchor, grids, decoder widths) as a
    case's model overrides."""
    m = preset(preset_name)[0]
    return {**{f: getattr(m, f) for f in SIZE_FIELDS}, "hash": {f: getattr(m.hash, f) for f in HASH_SIZE_FIELDS}}


CASES: dict[str, tuple[str, dict, dict]] = {
    "w7": ("window W=7 (paper), black background", {"window": 7, **NO_MOTION, **NO_CARVE},
           {"background_from_images": False, **SUM_VOLUME}),
    "w3": ("W=3, black background", {"window": 3, **NO_MOTION, **NO_CARVE}, {"background_from_images": False, **SUM_VOLUME}),
    "w1": ("W=1, black background", {"window": 1, **NO_MOTION, **NO_CARVE}, {"background_from_images": False, **SUM_VOLUME}),
    "w7-mean": ("W=7, mean image colour as background", {"window": 7, **NO_MOTION, **NO_CARVE}, MEAN_BG),
    "w3-mean": ("W=3, mean image colour as background", {"window": 3, **NO_MOTION, **NO_CARVE}, MEAN_BG),
    "w1-mean": ("W=1, mean image colour as background", {"window": 1, **NO_MOTION, **NO_CARVE}, MEAN_BG),
    # anchor motion (atgs.model.anchor_motion), over the mean colour
    "w7-fade": ("W=7, mean colour, anchors fade with their keyframe distance",
                {"window": 7, "temporal_fade": True, "anchor_velocity": False, **NO_CARVE}, MEAN_BG),
    "w7-fade-velocity": ("W=7, mean colour, anchors fade and move (velocity), random anchors not carved",
                         {**MOTION, **NO_CARVE}, MEAN_BG),
    "w7-fade-velocity-narrow": ("W=7, mean colour, fade and velocity, initial fade width 0.4 (not 0.6)",
                                {**MOTION, "fade_width": 0.4, **NO_CARVE}, MEAN_BG),
    # the 3D smoothing filter (atgs.model.smoothing) on top of anchor motion
    "w7-motion-smooth": ("W=7, mean colour, fade and velocity, 3D smoothing filter 0.2 px^2",
                         {**MOTION, "smoothing_3d": 0.2, **NO_CARVE}, MEAN_BG),
    # random anchors carved out of the space the keyframe points show empty (atgs.model.random_anchors)
    "w7-motion-carve": ("W=7, mean colour, fade and velocity, random anchors carved",
                        CARVED_MOTION, MEAN_BG),
    # on top of that: the offset regulariser and the scale-free volume loss (atgs.train.losses)
    "w7-motion-volume": ("as w7-motion-carve, volume loss mean over Gaussians in voxel units, 0.01",
                         CARVED_MOTION, {**MEAN_BG, **MEAN_VOXEL_VOLUME}),
    "w7-motion-offset": ("as w7-motion-volume, offset regulariser 0.01 beyond 1 voxel (the cpu preset "
                         "since 2026-11-25; 4 motion keyframes per interval up to machine-C)",
                         CARVED_MOTION, CPU_TRAIN),
    "w7-motion-offset-weak": ("as w7-motion-volume, offset regulariser 0.001 beyond 1 voxel",
                              CARVED_MOTION,
                              {**MEAN_BG, **MEAN_VOXEL_VOLUME, "lambda_offset": 0.001, "offset_free": 1.0}),
    # a random background colour per training step (evaluation still over the mean colour): the
    # model can no longer let the background show through its surfaces (mean alpha 0.93 before)
    "w7-motion-randbg": ("as w7-motion-offset, a random background colour per training step",
                         CARVED_MOTION, {**CPU_TRAIN, "random_background": True}),
    # a learned gain and bias per training camera and channel (atgs.train.exposure): neutral here,
    # where every camera is exposed alike, is what it should be
    "w7-motion-exposure": ("as w7-motion-offset, per-camera exposure (gain and bias per channel)",
                           CARVED_MOTION, {**CPU_TRAIN, "camera_exposure": "on"}),
    # DropGaussian (atgs.train.dropout): a random fraction of the Gaussians hidden per step, rising
    # to this rate over the run, against over-fitting the ten training views
    "w7-motion-drop10": ("as w7-motion-offset, Gaussian dropout rising to 0.1",
                         CARVED_MOTION, {**CPU_TRAIN, "drop_gaussians": 0.1}),
    "w7-motion-drop30": ("as w7-motion-offset, Gaussian dropout rising to 0.3",
                         CARVED_MOTION, {**CPU_TRAIN, "drop_gaussians": 0.3}),
    # steps no longer buy much at 20 minutes (8.6k steps alone: +0.1 dB over 5k side by side):
    # two training views per decoded frame, or the larger model of preset cpu-accurate
    "w7-motion-cams2": ("as w7-motion-offset, 2 training cameras per decoded frame",
                        CARVED_MOTION, {**CPU_TRAIN, "cameras_per_frame": 2}),
    # depth distortion (atgs.train.losses.depth_distortion): held-out pixels lose PSNR with their
    # depth error, and each ray's weights spread ~6 % of its depth after 20 minutes without it
    "w7-motion-distort3e-3": ("as w7-motion-offset, depth distortion 0.003",
                              CARVED_MOTION, {**CPU_TRAIN, "lambda_distortion": 0.003}),
    "w7-motion-distort1e-3": ("as w7-motion-offset, depth distortion 0.001",
                              CARVED_MOTION, {**CPU_TRAIN, "lambda_distortion": 0.001}),
    "w7-motion-distort1e-2": ("as w7-motion-offset, depth distortion 0.01",
                              CARVED_MOTION, {**CPU_TRAIN, "lambda_distortion": 0.01}),
    "w7-motion-large": ("as w7-motion-offset, the model sizes of preset cpu-accurate",
                        {**CARVED_MOTION, **model_sizes("cpu-accurate")}, CPU_TRAIN),
    # the other way: the smaller model of preset cpu-fast, for cheaper steps (a GPU run of the cpu
    # preset still gained 0.37 dB from 6.1k to 9.1k steps)
    "w7-motion-small": ("as w7-motion-offset, the model sizes of preset cpu-fast",
                        {**CARVED_MOTION, **model_sizes("cpu-fast")}, CPU_TRAIN),
    # moving content is under-fitted even in the training views after 20 minutes: its anchors
    # see only the views of their keyframe's time span
    "w7-motion-movinglr3": ("as w7-motion-offset, learning rates of the per-keyframe anchors x3",
                            CARVED_MOTION, {**CPU_TRAIN, "lr": {"moving_anchors": 3.0}}),
    "w7-motion-movinglr10": ("as w7-motion-offset, learning rates of the per-keyframe anchors x10",
                             CARVED_MOTION, {**CPU_TRAIN, "lr": {"moving_anchors": 10.0}}),
    "w7-motion-anchorlr3": ("as w7-motion-offset, learning rates of every anchor's feature and scale x3",
                            CARVED_MOTION, {**CPU_TRAIN, "lr": ANCHOR_LR3}),
    "w7-motion-anchorlr6": ("as w7-motion-offset, learning rates of every anchor's feature and scale x6",
                            CARVED_MOTION, {**CPU_TRAIN, "lr": {"anchor_feature": 0.045, "anchor_scaling": 0.042}}),
    "w7-motion-anchorlr3-spatial3": ("as w7-motion-anchorlr3, and the spatial grid's x3",
                                     CARVED_MOTION, {**CPU_TRAIN, "lr": {**ANCHOR_LR3, "spatial_grid": 0.0225}}),
    "w7-motion-anchorlr3-mlp2": ("as w7-motion-anchorlr3, and the decoder MLPs' x2",
                                 CARVED_MOTION, {**CPU_TRAIN, "lr": {**ANCHOR_LR3, "offset_init": 0.016,
                                                                     "opacity_init": 0.004, "cov": 0.008,
                                                                     "color_init": 0.016}}),
    # motion keyframes per geometry-keyframe interval (atgs-prepare --motion.per-interval, 8 by
    # default since 2026-11-25, 4 before: 41 / 21 keyframes here): more keyframes put anchors where the objects are at more times,
    # fewer give each keyframe's anchors more views
    "w7-motion-per2": ("as w7-motion-offset, prepared with --motion.per-interval 2 (11 motion keyframes)",
                       CARVED_MOTION, CPU_TRAIN),
    "w7-motion-per4": (("as w7-motion-offset, prepared with --motion.per-interval 4 (21 motion keyframes, "
                        "the default until 2026-11-25)"), CARVED_MOTION, CPU_TRAIN),
    "w7-motion-per8": (("as w7-motion-offset, prepared with --motion.per-interval 8 (41 motion keyframes, "
                        "the default since 2026-11-25)"), CARVED_MOTION, CPU_TRAIN),
    "w7-motion-temporallr5": ("as w7-motion-offset, learning rates of the temporal grids and MLPs x5",
                              CARVED_MOTION, {**CPU_TRAIN, "lr": {"temporal_init": 1e-3, "temporal_final": 1e-5,
                                                                  "temporal_mlp_init": 1e-2,
                                                                  "temporal_mlp_final": 1e-4}}),
}

# cases trained on the built-in scene with its motion points made again at another per-interval
MOTION_PER_INTERVAL = {"w7-motion-per2": 2, "w7-motion-per4": 4, "w7-motion-per8": 8}


@dataclass
class BudgetKnobs:
    cases: tuple[str, ...] = tuple(CASES)
    minutes: float = 8.0
    jobs: int = 2
    work_dir: Path = Path("/tmp/atgs-bench-knobs")
    out: Path = ROOT / "bench" / "results" / "budget_knobs.json"
    docs: Path = ROOT / "docs" / "training.md"
    tag: str = ""
    """Keep these runs as rows of their own, labelled with the tag, instead of replacing the cases'
    earlier rows: a baseline rerun on the day's machine next to new cases (`--tag rerun-2026-11-25`)."""
    worker: str = ""  # internal: run this one case in this process
    rescore: bool = False  # recompute the per-pixel split of existing runs (their checkpoints), no training


def built_in_scene() -> Path:
    from atgs.data.synth.videos import ensure_default_scene
    from atgs.io.cache import cache_dir

    return ensure_default_scene(cache_dir(), progress=True)


def motion_variant(scene_dir: Path, per_interval: int, work_dir: Path) -> Path:
    """A copy of the prepared built-in scene (frames hard-linked, the same keyframe points) whose
    motion points are made again at ``per_interval`` motion keyframes per geometry interval, as
    `atgs-prepare --motion.per-interval` makes them; cached in ``work_dir``."""
    import numpy as np

    from atgs.data.moving_points import MotionPointsConfig, motion_keyframes, motion_points
    from atgs.data.scene import MemoryScene, PreparedScene, compute_bounds, write_scene_metadata
    from atgs.io.atomic import atomic_dir, link_or_copy

    # named after the scene it derives from, so a new PREPARE_VERSION never reuses an older copy
    out = work_dir / f"scene-{scene_dir.parent.name}-{scene_dir.name}-motion-per{per_interval}"
    if (out / "scene.json").is_file():
        return out
    scene = PreparedScene.load(scene_dir)
    meta = json.loads((scene_dir / "scene.json").read_text())
    train = list(scene.train_indices)
    kfs = motion_keyframes(scene.num_frames, len(scene.keyframes), per_interval)
    mp = motion_points(lambda ci, f: scene.image_uint8(train[ci], f), [scene.cameras[i] for i in train],
                       scene.num_frames, kfs, compute_bounds(np.asarray(scene.points), [scene.cameras[i] for i in train]),
                       MotionPointsConfig(per_interval=per_interval), progress=False)
    with atomic_dir(out, True) as tmp:
        shutil.copytree(scene_dir / "images", tmp / "images", copy_function=link_or_copy)
        shutil.copy2(scene_dir / "synth.json", tmp / "synth.json")
        content = MemoryScene(scene.cameras, scene.num_frames, scene.fps, scene.keyframes, scene.points,
                              scene.point_keyframes, scene.test_cameras, point_colors=scene.point_colors,
                              **mp.scene_fields())
        write_scene_metadata(tmp, content, name=f"{scene.name}-motion-per{per_interval}",
                             source=scene.source, extra={"coverage": meta.get("coverage"),
                                                         "keyframe_points": meta.get("keyframe_points"),
                                                         "motion_points": mp.stats})
    return out


def case_scene(name: str, work_dir: Path) -> Path:
    """The prepared scene a case trains on: the built-in one, or its motion-points variant."""
    scene_dir = built_in_scene()
    if name in MOTION_PER_INTERVAL:
        scene_dir = motion_variant(scene_dir, MOTION_PER_INTERVAL[name], work_dir)
    return scene_dir


def run_case(args: BudgetKnobs, name: str) -> dict:
    from _splits import held_out_splits
    from atgs.data.scene import PreparedScene

    _, model_over, train_over = CASES[name]
    scene_dir = case_scene(name, args.work_dir)
    run = args.work_dir / f"run-{row_key(name, args.minutes, args.tag)}"
    tr = build_trainer(PreparedScene.load(scene_dir), run, "cpu", minutes=args.minutes, model=model_over,
                       train=train_over)
    timed = run_timed(tr, "renders")  # the final evaluation as atgs-train's (eval/ holds its images)
    ev = timed.eval
    return {"case": name, "what": CASES[name][0], "model_overrides": model_over, "train_overrides": train_over,
            "minutes": args.minutes, "steps": tr.step, "train_s": round(timed.seconds, 1), "anchors": tr.model.num_anchors,
            "keyframes": tr.model.num_keyframes, "psnr": round(ev["psnr"], 2),
            "ssim": round(ev["ssim"], 4), "views": ev["views"],
            "split": held_out_splits(run / "ckpt.pt", scene_dir), **run_stamp(), "tag": args.tag}


def row_key(case: str, minutes: float, tag: str = "") -> str:
    """Results are kept per case, budget and tag: the 8-minute runs under the case name, others with it."""
    key = case if minutes == 8 else f"{case}@{minutes:g}min"
    return f"{key}#{tag}" if tag else key


def table(rows: dict) -> str:
    lines = ["| case | minutes | run on | steps | anchors | PSNR | SSIM | moving | static | seen | unseen | change at window switches / other frames |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for key, r in sorted(rows.items(), key=lambda kv: (kv[1]["minutes"], list(CASES).index(kv[1]["case"]))):
        s = r["split"]
        what = CASES[r["case"]][0] if r["case"] in CASES else r["what"]  # the case's current wording
        what += f" ({r['tag']})" if r.get("tag") else ""
        lines.append(f"| {what} | {r['minutes']:g} | {r['date']} | {r['steps']:,} | {r['anchors']:,} | {r['psnr']:.2f} | {r['ssim']:.3f} | "
                     f"{s['psnr_moving']:.2f} | {s['psnr_static']:.2f} | {s['psnr_seen']:.2f} | {s['psnr_unseen']:.2f} | "
                     f"{s['psnr_change_switch']:.2f} / {s['psnr_change_steady']:.2f} |")
    r = next(iter(rows.values()))
    s = r["split"]
    lines += ["", f"Built-in large-motion scene, preset cpu, two runs at once with one "
              f"torch thread each (2-core machine). Rows run on different days, or tagged with another "
              f"machine, saw machines of different speed (the steps column): compare rows of one day and "
              f"machine. PSNR/SSIM: held-out cam00, all {r['views']} frames; "
              f"the split (every {s['every_nth_frame']}th frame): {s['moving_fraction']:.1%} of the pixels move, "
              f"{s['unseen_fraction']:.1%} show a surface no training camera sees; last column: the PSNR of the "
              f"change between consecutive frames (render against ground truth), over the pairs where the keyframe "
              f"window changes and over the others (popping lowers the first). `python bench/budget_knobs.py`."]
    return "\n".join(lines)


def main() -> None:
    args = tyro.cli(BudgetKnobs)
    if args.worker:
        print(json.dumps(run_case(args, args.worker)), flush=True)
        return
    unknown = [c for c in args.cases if c not in CASES]
    if unknown:
        sys.exit(f"bench/budget_knobs.py: unknown case(s) {unknown}; choose from {list(CASES)}")
    built_in_scene()  # prepared once, before the workers start
    args.work_dir.mkdir(parents=True, exist_ok=True)
    rows = json.loads(args.out.read_text())["cases"] if args.out.exists() else {}

    def one(name: str) -> dict:
        cmd = [sys.executable, __file__, "--worker", name, "--minutes", str(args.minutes),
               "--work-dir", str(args.work_dir), "--tag", args.tag]
        return run_worker(cmd, args.work_dir / f"{row_key(name, args.minutes, args.tag)}.log")

    if args.rescore:
        from _splits import held_out_splits

        def rescore(name: str) -> dict:
            return held_out_splits(args.work_dir / f"run-{name}" / "ckpt.pt", case_scene(rows[name]["case"], args.work_dir))

        names = [row_key(c, args.minutes, args.tag) for c in args.cases if row_key(c, args.minutes, args.tag) in rows]
        with ThreadPoolExecutor(max(1, args.jobs)) as pool:
            for name, split in zip(names, pool.map(rescore, names)):
                rows[name]["split"] = split
        publish({"cases": rows}, args.out, table(rows), args.docs, "budget-knobs")
        return

    with ThreadPoolExecutor(max(1, args.jobs)) as pool:
        for name, r in zip(args.cases, pool.map(one, args.cases)):
            print(f"[budget-knobs] {name} ({args.minutes:g} min): {r['psnr']:.2f} dB, {r['steps']} steps", flush=True)
            rows[row_key(name, args.minutes, args.tag)] = r
    publish({"cases": rows}, args.out, table(rows), args.docs, "budget-knobs")


if __name__ == "__main__":
    main()
