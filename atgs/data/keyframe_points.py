"""Keyframe points of a prepared scene: SIFT triangulation, dense stereo, and the fallback fill.

At each keyframe, from the training cameras (test cameras are held out):
1. pycolmap SIFT + known-pose triangulation (sparse, accurate); its points also set each
   camera's depth range and guide the choice of stereo sources;
2. PatchMatch stereo + cross-view fusion (:mod:`atgs.data.mvs`), when enabled;
3. where the points of 1 and 2 cover less than ``fill.below`` of a training camera's pixels, fill
   points in the space seen by at least two cameras through that camera's uncovered pixels, but
   not in the space the measured points prove empty (:mod:`atgs.geometry.free_space`);
4. the measured surfaces extended into the uncovered pixels near covered ones, at the depth of
   their neighbours (:mod:`atgs.data.mvs.extend`, ``fill.extend_reach``).
Coverage (:mod:`atgs.geometry.coverage`) of every camera by the measured points (1 + 2) is returned
for scene.json.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from atgs.cameras import Camera
from atgs.data.colmap_ops import ColmapOptions, triangulate_known_poses
from atgs.data.errors import DataError
from atgs.data.mvs import FillConfig, StereoConfig, stereo_points
from atgs.data.mvs.extend import extend_surfaces
from atgs.data.mvs.fill import frustum_fill
from atgs.data.mvs.stereo import stereo_steps
from atgs.data.mvs.views import check_camera_layout, depth_ranges
from atgs.data.scene import read_rgb
from atgs.geometry.coverage import coverage_mask, point_spacing, scene_coverage, working_camera
from atgs.geometry.free_space import carve
from atgs.geometry.rig_check import sparse_rig_warning

LOW_COVERAGE = 0.5  # warn below this mean coverage of the training cameras


@dataclass
class KeyframePoints:
    points: np.ndarray  # (P,3) float64
    colors: np.ndarray  # (P,3) uint8
    keyframes: np.ndarray  # (P,) int64, index into the keyframe list
    counts: dict = field(default_factory=dict)  # {"sift", "stereo", "fill", "extend"}: a list per keyframe
    coverage: dict = field(default_factory=dict)  # scene_coverage of the measured (non-fill) points


def keyframe_points(root: Path, cams: Sequence[Camera], test: Sequence[str], kfs: Sequence[int], ext: str, work: Path,
                    colmap: ColmapOptions, stereo: StereoConfig, fill: FillConfig,
                    depth_hints: Sequence[tuple[float, float]] | None = None, progress: bool = True,
                    where: str | None = None) -> KeyframePoints:
    """Points of every keyframe of the prepared frames under ``root/images``; ``where`` names the
    capture in error messages (default: ``root/images``, which may be a temporary folder)."""
    from tqdm import tqdm

    # Held-out cameras never feed the points: their images would leak into the held-out score.
    use_idx = [i for i, c in enumerate(cams) if c.name not in test]
    use = [cams[i] for i in use_idx]
    where = where or str(root / "images")
    check_camera_layout(use, where, held_out=len(cams) - len(use))
    hints = None if depth_hints is None else [depth_hints[i] for i in use_idx]
    P, C, K, fill_mask = [], [], [], []
    counts: dict[str, list[int]] = {"sift": [], "stereo": [], "fill": [], "extend": []}
    per_kf = stereo_steps(len(use), stereo) if stereo.enabled else 1
    with tqdm(total=len(kfs) * per_kf, desc="keyframe points", unit="cam" if stereo.enabled else "kf",
              disable=not progress) as bar:
        for j, f in enumerate(kfs):
            names = [f"{c.name}/{f:06d}{ext}" for c in use]
            sift, sift_rgb = triangulate_known_poses(root / "images", names, use, work / f"kf{j:04d}", colmap)
            keep = gross_outlier_mask(sift)
            sift, sift_rgb = sift[keep], sift_rgb[keep]
            images = [read_rgb(root / "images" / n) for n in names]
            pts, cols = [sift], [sift_rgb.astype(np.float32) / 255.0]
            n_stereo = 0
            if stereo.enabled:
                res = stereo_points(images, use, stereo, seed_points=sift if len(sift) else None, depth_hints=hints,
                                    on_camera=bar.update)
                pts.append(res.points)
                cols.append(res.colors)
                n_stereo = len(res.points)
            else:
                bar.update(1)
            measured = np.concatenate(pts)
            fpts, fcols = _fill(use, images, measured, hints, stereo, fill, seed=j)
            if fill.enabled and len(measured) == 0 and len(fpts) == 0:
                raise DataError(f"{where}: no two cameras see a common region (stereo, SIFT and the "
                                "frustum intersection found nothing); check the poses (world-to-camera vs "
                                "camera-to-world, units) and that the cameras overlap")
            epts, ecols = np.zeros((0, 3)), np.zeros((0, 3), np.float32)
            if fill.enabled and len(measured) >= 2:
                epts, ecols = extend_surfaces(use, images, measured, point_spacing(measured), stereo.long_side,
                                              fill.extend_reach, fill.extend_points, seed=j)
            for arr, c, is_fill in ((measured, np.concatenate(cols), False), (fpts, fcols, True),
                                    (epts, ecols, True)):
                P.append(arr)
                C.append(np.clip(np.round(c * 255), 0, 255).astype(np.uint8))
                K.append(np.full(len(arr), j, np.int64))
                fill_mask.append(np.full(len(arr), is_fill))
            counts["sift"].append(int(len(sift)))
            counts["stereo"].append(int(n_stereo))
            counts["fill"].append(int(len(fpts)))
            counts["extend"].append(int(len(epts)))
    pts, cols, kf, is_fill = (np.concatenate(x) for x in (P, C, K, fill_mask))
    cov = scene_coverage(cams, pts[~is_fill], kf[~is_fill], len(kfs), test, stereo.long_side)
    _report(counts, cov, test, progress, use)
    return KeyframePoints(pts, cols, kf, counts, cov)


def _fill(cams: Sequence[Camera], images: Sequence[np.ndarray], measured: np.ndarray,
          hints: Sequence[tuple[float, float]] | None, stereo: StereoConfig, fill: FillConfig,
          seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Fill points through the uncovered pixels of the cameras covered less than ``fill.below``."""
    if not fill.enabled:
        return np.zeros((0, 3)), np.zeros((0, 3), np.float32)
    spacing = point_spacing(measured) if len(measured) >= 2 else 0.0
    masks = []
    for cam in cams:
        if len(measured) < 2:
            masks.append(np.ones((1, 1), bool))
            continue
        covered = coverage_mask(working_camera(cam, stereo.long_side), measured, spacing)
        masks.append(~covered if covered.mean() < fill.below else None)
    if all(m is None for m in masks):
        return np.zeros((0, 3)), np.zeros((0, 3), np.float32)
    ranges = depth_ranges(cams, measured if len(measured) else None, hints=hints)
    pts, cols = frustum_fill(cams, ranges, fill, images=images, masks=masks, seed=seed)
    if len(measured) and len(pts):  # never where a camera sees a measured surface behind: floaters in new views
        keep = carve(pts, measured, cams)
        pts, cols = pts[keep], cols[keep]
    return pts, cols


def _report(counts: dict, cov: dict, test: Sequence[str], progress: bool, cams: Sequence[Camera]) -> None:
    """The keyframe points' one-line summary and its warnings (``cams``: the training cameras)."""
    k = len(counts["sift"])
    line = (f"keyframe points (mean of {k}): {np.mean(counts['sift']):.0f} SIFT + {np.mean(counts['stereo']):.0f} "
            f"stereo + {np.mean(counts['fill']):.0f} fill + {np.mean(counts['extend']):.0f} "
            f"extension; coverage of the training cameras by SIFT + stereo {cov['mean']:.0%}")
    views = cov["views_per_pixel"]
    if views["mean"]:  # 0: no measured pixel, nothing to count
        line += f", seen by {views['mean']:.1f} training cameras per measured pixel"
    if cov["test_cameras"]:
        line += "; test " + ", ".join(f"{n} {c:.0%} seen by {views['test_cameras'][n]:.1f}"
                                      for n, c in cov["test_cameras"].items())
    if progress:
        print(line, file=sys.stderr)
    if sum(counts["fill"]):
        print(f"warning: stereo and SIFT covered too little of some cameras (below the --fill.below share); "
              f"{sum(counts['fill'])} fill points in the space seen by two cameras were added so training can "
              "start", file=sys.stderr)
    if cov["mean"] < LOW_COVERAGE:
        print(f"warning: the keyframe points cover only {cov['mean']:.0%} of the training cameras' pixels "
              "(textureless surfaces, wide baselines or few cameras); expect a slower, rougher start",
              file=sys.stderr)
    sparse = sparse_rig_warning(cams, views["mean"])
    if sparse is not None:
        print(sparse, file=sys.stderr)


def gross_outlier_mask(pts: np.ndarray, margin: float = 0.5) -> np.ndarray:
    """Keep points inside the 1-99 percentile box grown by ``margin`` of its size on each side.

    Sparse triangulation leaves a few points far along poorly conditioned rays (e.g. metres
    below the ground); they would become floaters when used as anchors.
    """
    if len(pts) < 50:
        return np.ones(len(pts), bool)
    lo, hi = np.percentile(pts, 1, axis=0), np.percentile(pts, 99, axis=0)
    ext = (hi - lo) * margin
    return np.all((pts >= lo - ext) & (pts <= hi + ext), axis=1)
