"""``atgs-prepare``: any supported multi-view video layout -> one prepared scene directory.

Steps (each long one shows a progress bar):
1. detect/open the source and check that every camera has the same number of frames;
2. cameras: from the dataset's poses, checked against the training cameras' first selected
   frames (atgs.data.pose_check: camera-to-world matrices filed as world-to-camera are read the
   right way round), or pycolmap SfM on the first selected frame (static rig);
3. frames: decode lazily, undistort when the model has distortion, downscale, write PNG/JPG;
   foreground masks (of the training cameras that have them) the same way, kept where half an
   output pixel is foreground; held-out cameras' masks are never read;
4. keyframe points at each of K keyframes (atgs.data.keyframe_points): pycolmap SIFT +
   triangulation with fixed poses, CPU PatchMatch stereo fused across views, and a fill of the
   space seen by two cameras where both leave pixels uncovered; coverage per camera;
5. points on moving content at per_interval times as many keyframes, from motion masks and their
   visual hull (atgs.data.moving_points), cheap where stereo is not;
6. scene.json + points.ply (+ motion_points.ply); the directory is built as ``OUT.tmp-xxxx`` and renamed at the end.
"""

from __future__ import annotations

import shutil
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import tyro
from PIL import Image

from atgs.cameras import Camera
from atgs.io.atomic import atomic_dir, check_output_dir
from atgs.data.colmap_ops import ColmapOptions, sfm_static_cameras
from atgs.data.errors import DataError
from atgs.data.keyframe_points import keyframe_points
from atgs.data.moving_points import MotionPoints, MotionPointsConfig, motion_keyframes, motion_points
from atgs.data.mvs import FillConfig, StereoConfig
from atgs.data.mvs.views import check_camera_layout
from atgs.data.pose_check import PoseCheckConfig, check_poses
from atgs.data.scene import (MemoryScene, compute_bounds, frame_path, mask_path, read_mask, read_rgb, save_frame,
                             save_mask, write_scene_metadata)
from atgs.data.sources import Source, SourceFormat, open_source
from atgs.data.undistort import apply_undistort_map, build_undistort_map
from atgs.timeline import evenly_spaced


@dataclass(frozen=True)
class PrepareConfig:
    """Turn a multi-view video dataset into a prepared ATGS scene."""

    src: Annotated[Path, tyro.conf.Positional]
    """Dataset directory (N3DV, COLMAP frame folders, EasyVolcap, Dynamic 3D Gaussians, plain videos or image
    folders)."""
    out: Path
    """Output directory; written atomically, never half-written."""
    format: SourceFormat = "auto"
    """Input layout; 'auto' detects it."""
    downscale: float = 1.0
    """Divide the resolution by this factor (2 = half width and height)."""
    frames: str | None = None
    """Frame range 'start:end[:step]' (end exclusive, Python style; empty parts allowed)."""
    start: int | None = None
    """First frame (alternative to --frames)."""
    end: int | None = None
    """End frame, exclusive (alternative to --frames)."""
    test_cams: tuple[str, ...] | None = None
    """Held-out camera names or indices (default: the dataset's convention, e.g. cam00)."""
    keyframes: int = 5
    """Number of evenly spaced keyframes at which points are reconstructed."""
    stereo: StereoConfig = StereoConfig()
    """Dense multi-view stereo of the keyframe points (docs/data.md)."""
    fill: FillConfig = FillConfig()
    """Fallback points where stereo and SIFT leave cameras uncovered (docs/data.md)."""
    motion: MotionPointsConfig = MotionPointsConfig()
    """Points on moving content at more keyframes, from motion masks (docs/data.md)."""
    trim_mismatch: bool = False
    """If cameras have different frame counts, keep the shortest length (with a warning)."""
    overwrite: bool = False
    """Replace an existing output directory (only after the new one is complete)."""
    image_format: Literal["png", "jpg"] = "png"
    """Frame file format in the prepared scene."""
    sift_max_image_size: int = 1600
    """Longest image side used for SIFT."""
    sfm_camera_model: str = "SIMPLE_RADIAL"
    """COLMAP camera model estimated by SfM when the source has no poses."""
    sfm_shared_intrinsics: bool = True
    """SfM: one intrinsic model for all cameras (identical cameras); else one per camera."""
    fps: float | None = None
    """Frame rate of the source (default: from the videos; 30 for image folders and Dynamic 3D Gaussians)."""
    name: str | None = None
    """Scene name (default: the output directory name)."""
    check_poses: bool = True
    """Check the dataset's poses against its training cameras' first frames (epipolar agreement of
    SIFT matches) and read camera-to-world matrices filed as world-to-camera correctly;
    --no-check-poses uses the poses as given."""
    progress: bool = True
    """Show progress bars."""


def parse_frame_range(spec: str | None, start: int | None, end: int | None, n: int) -> range:
    """Selected source frames. ``spec`` is 'start:end[:step]' (end exclusive)."""
    step = 1
    if spec:
        parts = spec.split(":")
        if len(parts) not in (2, 3):
            raise DataError(f"--frames {spec!r}: expected start:end or start:end:step")
        try:
            vals = [int(p) if p.strip() else None for p in parts]
        except ValueError:
            raise DataError(f"--frames {spec!r}: start, end and step must be integers") from None
        if start is not None or end is not None:
            raise DataError("--frames cannot be combined with --start/--end")
        start, end = vals[0], vals[1]
        step = vals[2] if len(vals) == 3 and vals[2] is not None else 1
    s = 0 if start is None else start
    e = n if end is None else end
    if s < 0:
        s += n
    if e < 0:
        e += n
    if step < 1:
        raise DataError(f"--frames: step must be >= 1, got {step}")
    e = min(e, n)
    if not 0 <= s < e:
        raise DataError(f"frame range {s}:{e} is empty; the source has {n} frames per camera")
    return range(s, e, step)


MIN_TRAIN_CAMERAS = 2  # keyframe points need two views, and held-out views never feed the model


def resolve_test_cams(spec: tuple[str, ...] | None, names: list[str], default: list[str],
                      where: str = "the capture") -> list[str]:
    """The held-out cameras: ``spec`` (names or indices), else the dataset's convention
    ``default`` unless it would leave fewer than two training cameras; then none, with a note (a
    two-camera rig trains on both). An explicit ``spec`` that leaves one training camera is an
    error: its images would be the only ones the points could come from."""
    if spec is None:
        test = [n for n in default if n in names]
        if test and len(names) - len(test) < MIN_TRAIN_CAMERAS:
            if len(names) >= MIN_TRAIN_CAMERAS:
                print(f"note: {where} has {len(names)} cameras: none held out (the convention would hold out "
                      f"{', '.join(test)} and leave one to train on), so atgs-train scores a training view; "
                      "a third camera gives a held-out view", file=sys.stderr)
            return []
        return test
    out = []
    for s in spec:
        for item in str(s).split(","):
            item = item.strip()
            if not item:
                continue
            if item in names:
                out.append(item)
            elif item.lstrip("-").isdigit() and -len(names) <= int(item) < len(names):
                out.append(names[int(item)])
            else:
                raise DataError(f"--test-cams {item!r}: no such camera (cameras: {', '.join(names)})")
    out = sorted(set(out), key=names.index)
    train = [n for n in names if n not in out]
    if out and len(train) < MIN_TRAIN_CAMERAS:
        left = f"only {train[0]} is left" if train else "none is left"
        raise DataError(f"{where}: --test-cams {','.join(out)} holds out all but {len(train)} of the {len(names)} "
                        f"cameras ({left}); the keyframe points need {MIN_TRAIN_CAMERAS} training cameras and never "
                        "use held-out ones: hold out fewer (--test-cams with no names holds out none)")
    return out


def check_frame_counts(src: Source, trim: bool) -> int:
    counts = src.num_frames
    n = min(counts)
    if max(counts) != n:
        short = int(np.argmin(counts))
        longest = max(counts)
        where = src.extra.get("missing", {}).get(src.camera_names[short]) or src.file_of(short)
        msg = (f"{where}: camera {src.camera_names[short]} has {counts[short]} frames but others have up to "
               f"{longest}")
        if not trim:
            raise DataError(msg + "; pass --trim-mismatch to keep the first " + str(n) + " frames of every camera")
        print(f"warning: {msg}; trimming every camera to {n} frames", file=sys.stderr)
    return n


def prepare(cfg: PrepareConfig) -> Path:
    """Run the whole ingest; returns the prepared directory."""
    t0 = time.perf_counter()
    out = Path(cfg.out)
    check_output_dir(out, cfg.overwrite)  # fail before any slow work
    if cfg.downscale < 1.0:
        raise DataError(f"--downscale {cfg.downscale}: must be >= 1 (2 halves the resolution)")
    if cfg.keyframes < 1:
        raise DataError(f"--keyframes {cfg.keyframes}: must be >= 1")
    if cfg.fps is not None and cfg.fps <= 0:
        raise DataError(f"--fps {cfg.fps}: must be positive")
    src = open_source(Path(cfg.src), cfg.format)
    n_src = check_frame_counts(src, cfg.trim_mismatch)
    sel = parse_frame_range(cfg.frames, cfg.start, cfg.end, n_src)
    num_frames = len(sel)
    test = resolve_test_cams(cfg.test_cams, src.camera_names, src.default_test, where=str(cfg.src))
    masked = _mask_cameras(src, test, sel)
    colmap_opts = ColmapOptions(max_image_size=cfg.sift_max_image_size)
    timings: dict[str, float] = {}
    with atomic_dir(out, cfg.overwrite) as tmp:
        work = tmp / "_work"
        cams = src.cameras
        if cams is None:
            t = time.perf_counter()
            cams = _sfm_cameras(src, sel[0], work / "sfm", cfg, colmap_opts, test)
            timings["sfm"] = time.perf_counter() - t
        cams = [_match_frame_size(c, wh, src.file_of(i)) for i, (c, wh) in enumerate(zip(cams, src.sizes))]
        if src.cameras is not None and cfg.check_poses:  # SfM poses agree with the frames by construction
            t = time.perf_counter()
            cams = _checked_poses(src, cams, test, sel[0], work / "pose_check", cfg, colmap_opts)
            timings["pose_check"] = time.perf_counter() - t
        _note_init_points(src)  # its hints follow the cameras as read
        out_cams = [_output_camera(c, cfg.downscale) for c in cams]
        t = time.perf_counter()
        ext = "." + cfg.image_format
        _extract_frames(tmp, src, cams, out_cams, sel, ext, masked, cfg.progress)
        timings["frames"] = time.perf_counter() - t
        t = time.perf_counter()
        kfs = evenly_spaced(num_frames, cfg.keyframes)  # the model's keyframe rule
        hints = src.extra.get("near_far")
        kp = keyframe_points(tmp, out_cams, test, kfs, ext, work, colmap_opts, cfg.stereo, cfg.fill,
                             depth_hints=[tuple(x) if x else None for x in hints] if hints else None,
                             progress=cfg.progress, where=str(cfg.src))
        timings["points"] = time.perf_counter() - t
        t = time.perf_counter()
        motion = _motion_points(tmp, out_cams, test, num_frames, ext, kp, cfg, masked)
        timings["motion_points"] = time.perf_counter() - t
        shutil.rmtree(work, ignore_errors=True)
        fps = (cfg.fps or src.fps) / sel.step
        source = {"path": str(Path(cfg.src).resolve()), "format": src.kind, "frames": [sel.start, sel.stop, sel.step],
                  "downscale": cfg.downscale, "source_frames": n_src, **{k: v for k, v in src.extra.items()
                                                                          if k not in ("missing",)}}
        synth_side = Path(cfg.src) / "synth.json"
        if synth_side.is_file():  # keep the ground truth description with the prepared scene
            shutil.copy2(synth_side, tmp / "synth.json")
            source["synth"] = "synth.json"
        timings["total"] = time.perf_counter() - t0
        source["timings_s"] = {k: round(v, 2) for k, v in timings.items()}
        # a scene with few points takes its bounds from the cameras: the training cameras only
        # (float32 points, as write_scene_metadata would take them)
        bounds = compute_bounds(np.asarray(kp.points, np.float32), [c for c in out_cams if c.name not in test])
        content = MemoryScene(out_cams, num_frames, fps, kfs, kp.points, kp.keyframes, test, point_colors=kp.colors,
                              bounds=bounds,
                              **(motion.scene_fields() if motion is not None else {}))
        write_scene_metadata(tmp, content, name=cfg.name or out.name, source=source,
                             extra={"coverage": kp.coverage, "keyframe_points": kp.counts,
                                    "motion_points": motion.stats if motion is not None else {"enabled": False}},
                             masks=masked)
    return out


def _mask_cameras(src: Source, test: list[str], sel: range) -> list[str]:
    """The training cameras whose masks the scene keeps (held-out cameras' are never read), after
    checking that each has a mask of every selected frame; one line names the training cameras
    that have none when others do: their motion masks come from their frames instead."""
    if src.masks is None:
        return []
    train = [i for i, n in enumerate(src.camera_names) if n not in test]
    masked = [src.camera_names[i] for i in train if src.camera_has_masks(i, sel)]
    without = [src.camera_names[i] for i in train if src.camera_names[i] not in masked]
    if masked and without:
        print(f"note: {src.root}: training camera(s) {', '.join(without)} have no masks; they prepare and train "
              "without (their motion masks come from the frames' difference from their background)", file=sys.stderr)
    return masked


def _note_init_points(src: Source) -> None:
    """One line on what a capture's initial point cloud is used for (only hints; sources.point_hints)."""
    n = src.extra.get("init_points")
    if n is not None:
        hinted = sum(h is not None for h in src.extra["near_far"])
        print(f"note: {src.root / 'init_pt_cld.npz'}: {n} points, used only as depth-range hints for the stereo of "
              f"{hinted} of {len(src.camera_names)} cameras (never as scene points)", file=sys.stderr)


def _checked_poses(src: Source, cams: list[Camera], test: list[str], frame: int, work: Path, cfg: PrepareConfig,
                   opts: ColmapOptions) -> list[Camera]:
    """The dataset's poses under the reading that the training cameras' first frames agree with
    (atgs.data.pose_check); a held-out camera's frames are never read."""
    # a rig no reading can use (one camera, all at one spot) is its own error, not a question of convention
    check_camera_layout([c for c in cams if c.name not in test], str(cfg.src), held_out=len(test))
    frames = []
    for ci, cam in enumerate(cams):
        if cam.name in test:
            frames.append(None)
            continue
        _, img = next(src.frames(ci, [frame]))
        _check_frame_size(src, ci, frame, img, cam)
        frames.append(_resample(img, replace(cam, dist=None), build_undistort_map(cam) if cam.dist is not None else None))
    checked = check_poses(cams, frames, src.world_mirror, src.calibration or src.root, work, PoseCheckConfig(), opts,
                          cfg.progress, by_layout=src.poses_by_hand)
    if checked is not cams:
        src.depth_hints(checked)  # the capture's own points hint depths along the cameras as now read
        src.extra["poses_read_as"] = "camera-to-world"
    return checked


def _check_frame_size(src: Source, ci: int, frame: int, img: np.ndarray, cam: Camera) -> None:
    if img.shape[:2] != (cam.height, cam.width):
        raise DataError(f"{src.file_of(ci)}: frame {frame} is {img.shape[1]}x{img.shape[0]}, "
                        f"expected {cam.width}x{cam.height}")


def _extract_frames(root: Path, src: Source, cams: list[Camera], out_cams: list[Camera], sel: range, ext: str,
                    masked: list[str], progress: bool) -> None:
    """Every selected frame onto its output camera, and its mask for the ``masked`` cameras."""
    from tqdm import tqdm

    with tqdm(total=len(cams) * len(sel), desc="extract frames", unit="img", disable=not progress) as bar:
        for ci, (cam, ocam) in enumerate(zip(cams, out_cams)):
            (root / "images" / ocam.name).mkdir(parents=True)
            has_mask = src.camera_names[ci] in masked
            if has_mask:
                (root / "masks" / ocam.name).mkdir(parents=True)
            umap = build_undistort_map(cam) if cam.dist is not None else None
            for j, (_, img) in enumerate(src.frames(ci, sel)):
                _check_frame_size(src, ci, sel[j], img, cam)
                save_frame(root, ocam, j, _resample(img, ocam, umap), ext)
                if has_mask:
                    save_mask(root, ocam, j, _output_mask(src, ci, sel[j], cam, ocam, umap))
                bar.update(1)


def _resample(img: np.ndarray, ocam: Camera, umap) -> np.ndarray:
    """``img`` undistorted (when ``umap`` is given) and box-downscaled to ``ocam``'s size: frames
    (uint8) and masks (float) alike."""
    if umap is not None:
        img = apply_undistort_map(umap, img).reshape(img.shape)
    if img.shape[:2] != (ocam.height, ocam.width):
        img = np.asarray(Image.fromarray(img).resize((ocam.width, ocam.height), Image.BOX))
    return img


def _output_mask(src: Source, ci: int, frame: int, cam: Camera, ocam: Camera, umap) -> np.ndarray:
    """Source mask -> output camera: the share of foreground in each output pixel (the frames' box
    filter), foreground from one half up, so mask and frame edges stay aligned."""
    m = src.mask(ci, frame)
    if m.shape != (cam.height, cam.width):
        raise DataError(f"{src.masks[ci][frame]}: mask is {m.shape[1]}x{m.shape[0]}, its image {cam.width}x{cam.height}")
    return _resample(m.astype(np.float32), ocam, umap) >= 0.5


def _motion_points(root: Path, cams: list[Camera], test: list[str], num_frames: int, ext: str,
                   kp, cfg: PrepareConfig, masked: list[str]) -> MotionPoints | None:
    """Moving-content points at the motion keyframes, from the training cameras' frames."""
    if not cfg.motion.enabled:
        return None
    cfg.motion.validate()
    train = [c for c in cams if c.name not in test]  # two or more: keyframe_points checked
    kfs = motion_keyframes(num_frames, cfg.keyframes, cfg.motion.per_interval)
    box = compute_bounds(kp.points, train)  # (without points: the box the training cameras see)
    # a capture's foreground masks, where it has them, are the moving content (stage captures:
    # the performers); else, camera by camera, the frames' difference from their background
    has = set(masked)

    def masks(ci: int, f: int) -> np.ndarray | None:
        return read_mask(mask_path(root, train[ci].name, f)) if train[ci].name in has else None

    mp = motion_points(lambda ci, f: read_rgb(frame_path(root, train[ci].name, f, ext)), train, num_frames, kfs, box,
                       cfg.motion, progress=cfg.progress, mask_of=masks if has else None)
    if cfg.progress:
        n = mp.stats["points"]
        print(f"motion points: {sum(n)} at {mp.stats['keyframes']} keyframes (mean {np.mean(n) if n else 0:.0f}); "
              f"{mp.stats['moving_fraction']:.1%} of the pixels move", file=sys.stderr)
    return mp


def _match_frame_size(cam: Camera, size: tuple[int, int], where: Path) -> Camera:
    """Calibrations are often made at full resolution and the frames stored smaller: rescale the
    intrinsics when the aspect ratio agrees, refuse otherwise."""
    w, h = size
    if (cam.width, cam.height) == (w, h):
        return cam
    if abs(w / h - cam.width / cam.height) > 0.01 * (w / h):
        raise DataError(f"{where}: frames are {w}x{h} but the camera model says {cam.width}x{cam.height} "
                        "(different aspect ratio); check that the calibration belongs to these frames")
    print(f"warning: {where}: frames are {w}x{h}, calibration is {cam.width}x{cam.height}; rescaling the "
          "intrinsics", file=sys.stderr)
    K = cam.K.copy()
    K[0] *= w / cam.width
    K[1] *= h / cam.height
    return replace(cam, width=w, height=h, K=K)


def _output_camera(cam: Camera, downscale: float) -> Camera:
    c = replace(cam, dist=None)
    return c if downscale == 1.0 else c.scaled(1.0 / downscale)


def _sfm_cameras(src: Source, frame: int, work: Path, cfg: PrepareConfig, opts: ColmapOptions,
                 test: list[str]) -> list[Camera]:
    """SfM on the training cameras' first frames; the held-out ``test`` cameras are registered
    after, against that reconstruction, so they change none of the training cameras' values."""
    from tqdm import tqdm

    img_dir = work / "images"
    img_dir.mkdir(parents=True)
    names = []
    for ci, name in enumerate(tqdm(src.camera_names, desc="SfM: first frames", disable=not cfg.progress)):
        for _, img in src.frames(ci, [frame]):
            Image.fromarray(img).save(img_dir / f"{name}.png")
        names.append(f"{name}.png")
    if cfg.progress:
        print(f"running SfM on {len(names) - len(test)} training cameras"
              + (f", then registering {len(test)} held-out" if test else "") + " (pycolmap, CPU)...", file=sys.stderr)
    return sfm_static_cameras(img_dir, names, src.camera_names, work, opts, cfg.sfm_camera_model,
                              cfg.sfm_shared_intrinsics, source=src.root, held_out=test)
