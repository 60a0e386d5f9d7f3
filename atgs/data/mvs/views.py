"""Cameras and images at the working resolution, per-camera depth ranges, and the choice of
source cameras for each reference camera."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from PIL import Image

from atgs.cameras import Camera
from atgs.data.errors import DataError
from atgs.geometry.coverage import working_camera
from atgs.geometry.projection import project
from atgs.geometry.rays import grid_rays, to_world
from atgs.geometry.seen_space import layout_depth_range, median_baseline, meeting_depth

# Source-camera choice: triangulation angles near PEAK_DEG are best; smaller angles give poor
# depth resolution, larger ones distort the matching windows (Goesele et al. 2007, MVSNet).
PEAK_DEG, SIGMA_BELOW_DEG, SIGMA_ABOVE_DEG, MIN_ANGLE_DEG = 12.0, 4.0, 20.0, 1.0
# Without seed points a source must score at least this (view_scores): measured on synthetic rigs,
# pairs 36-60 degrees apart score 0.05-0.5 and gave accurate points, pairs 77-90 degrees apart
# 0.01-0.03 and gave floaters (median error 8 % of the rig's radius).
NO_SEED_MIN_SCORE = 0.04


@dataclass
class View:
    """One camera at the working resolution with its image: ``gray`` (H,W) and ``rgb`` (H,W,3) in [0,1]."""

    cam: Camera
    gray: torch.Tensor
    rgb: torch.Tensor


def make_view(image: np.ndarray, cam: Camera, long_side: int) -> View:
    """Box-downsample an (H,W,3) uint8 image to the working resolution."""
    wc = working_camera(cam, long_side)
    img = np.asarray(image)
    if img.shape[:2] != (cam.height, cam.width):
        raise ValueError(f"image of {cam.name} is {img.shape[1]}x{img.shape[0]}, camera says {cam.width}x{cam.height}")
    if (wc.width, wc.height) != (cam.width, cam.height):
        img = np.asarray(Image.fromarray(img).resize((wc.width, wc.height), Image.BOX))
    rgb = torch.from_numpy(np.array(img[..., :3], dtype=np.float32)) / 255.0
    gray = rgb @ torch.tensor([0.299, 0.587, 0.114])
    return View(wc, gray.contiguous(), rgb)


# --- depth ranges ----------------------------------------------------------------------------

def check_camera_layout(cams: Sequence[Camera], where: str = "cameras", held_out: int = 0) -> None:
    """One-line errors for layouts no multi-view method can use (``cams``: the training cameras;
    ``held_out``: how many test cameras were set aside)."""
    if len(cams) < 2:
        raise DataError(f"{where}: {len(cams)} training camera(s)"
                        + (f" besides {held_out} held out" if held_out else "")
                        + "; depth needs at least 2 cameras at different positions"
                        + (" (hold out fewer test cameras with --test-cams)" if held_out else ""))
    c = np.array([cam.center for cam in cams])
    spread = float(np.linalg.norm(c - c.mean(0), axis=1).max())
    if not np.isfinite(c).all():
        raise DataError(f"{where}: a camera pose is not finite; check the poses")
    if spread < 1e-9 * max(1.0, float(np.abs(c).max())):
        raise DataError(f"{where}: all {len(cams)} cameras are at the same position, so no depth can be "
                        "triangulated; the scene needs cameras at different positions")


def triangulable_depth_range(cam: Camera, cams: Sequence[Camera], n_side: int = 16, n_depth: int = 64,
                             min_share: float = 0.05) -> tuple[float, float] | None:
    """Near/far of ``cam`` from the camera layout alone: the depths along its rays where stereo can
    work, i.e. another camera of ``cams`` sees the point (in front, inside its image) at a useful
    triangulation angle (the source weight of :func:`view_scores`). Mere covisibility is not
    enough: on a dome the opposite cameras see the space right at this camera's lens, and the
    neighbours see far beyond the scene. The range spans the depths whose mean weight over the
    rays reaches ``min_share`` of the best depth's, widened like the seeds' (x0.6, x1.6); depths
    are searched over 10^-3 to 10^4 median baselines (no units assumed). None when nothing
    qualifies."""
    others = [c for c in cams if c is not cam and not np.allclose(c.center, cam.center)]
    if not others:
        return None
    scale = median_baseline(cams)
    rays = grid_rays(cam, n_side)
    depths = np.geomspace(1e-3 * scale, 1e4 * scale, n_depth)
    X = to_world(cam, (rays[None] * depths[:, None, None]).reshape(-1, 3))  # (depth, ray) world points
    ri = X - cam.center
    ri /= np.linalg.norm(ri, axis=1, keepdims=True)
    best = np.zeros(len(X))
    for o in others:
        _, _, z, inside = project(o, X)
        rj = X - o.center
        rj /= np.linalg.norm(rj, axis=1, keepdims=True)
        deg = np.degrees(np.arccos(np.clip((ri * rj).sum(1), -1, 1)))
        best = np.maximum(best, (inside & (z > 1e-3 * scale)) * _angle_weight(deg))
    score = best.reshape(n_depth, -1).mean(1)
    if score.max() <= 0:
        return None
    ok = np.nonzero(score >= min_share * score.max())[0]
    return 0.6 * float(depths[ok[0]]), 1.6 * float(depths[ok[-1]])


def depth_ranges(cams: Sequence[Camera], points: np.ndarray | None, min_points: int = 20,
                 hints: Sequence[tuple[float, float]] | None = None) -> list[tuple[float, float]]:
    """(near, far) per camera: the 1-99% depths of the seed points it sees, widened (x0.6, x1.6);
    without enough seeds, the depths where another camera can triangulate (:func:`triangulable_depth_range`),
    narrowed to within 10x of the dataset's near/far hint where there is one (a hint can be wrong
    by that much either way: loose LLFF bounds, hand-written files); else the layout's guess
    (:func:`layout_depth_range`)."""
    pts = np.zeros((0, 3)) if points is None else np.asarray(points, np.float64).reshape(-1, 3)
    out = []
    for i, cam in enumerate(cams):
        z = np.zeros(0)
        if len(pts):
            _, _, z, inside = project(cam, pts)
            z = z[inside]
        if len(z) >= min_points:
            near, far = 0.6 * float(np.percentile(z, 1)), 1.6 * float(np.percentile(z, 99))
        else:
            near, far = layout_depth_range(cam, cams)
            seen = triangulable_depth_range(cam, cams)
            if seen is not None:  # where stereo can work, within the layout's guess where they overlap
                lo, hi = max(near, seen[0]), min(far, seen[1])
                near, far = (lo, hi) if lo < hi else seen
            hint = hints[i] if hints is not None else None
            if hint is not None and 0 < hint[0] < hint[1]:
                lo, hi = max(near, hint[0] / HINT_SLACK), min(far, hint[1] * HINT_SLACK)
                if lo < hi:  # a hint the layout contradicts altogether is ignored
                    near, far = lo, hi
        out.append((near, max(far, 1.5 * near)))
    return out


HINT_SLACK = 10.0  # a dataset's near/far is trusted to within this factor


# --- source camera choice --------------------------------------------------------------------

def _angle_weight(deg: np.ndarray) -> np.ndarray:
    sigma = np.where(deg < PEAK_DEG, SIGMA_BELOW_DEG, SIGMA_ABOVE_DEG)
    w = np.exp(-((deg - PEAK_DEG) ** 2) / (2 * sigma**2))
    return np.where(deg < MIN_ANGLE_DEG, 0.0, w)


def sample_view_points(cam: Camera, near: float, far: float, n_side: int = 12, depths: int = 3) -> np.ndarray:
    """World points on a grid of pixels at ``depths`` depths spread in inverse depth over [near, far]."""
    rays = grid_rays(cam, n_side)
    inv = np.linspace(1 / near, 1 / far, depths + 2)[1:-1]
    return to_world(cam, np.concatenate([rays / i for i in inv]))


def view_scores(cams: Sequence[Camera], ranges: Sequence[tuple[float, float]],
                points: np.ndarray | None = None, min_points: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """(N,N) score of camera j as a source for reference i: the mean, over points the reference
    sees (seed points, else a grid of its rays at eight depths about where a converging rig's
    axes meet, or over its range), of ``j sees it`` x a weight of the triangulation angle that
    peaks at PEAK_DEG and is 0 below MIN_ANGLE_DEG; and (N,N) the overlap: the fraction of those
    points j sees at all. Without seeds nothing confirms the geometry, so a source scoring below
    NO_SEED_MIN_SCORE (a pair about 70 degrees apart) scores 0: such wide pairs gave floaters."""
    n = len(cams)
    pts = None if points is None else np.asarray(points, np.float64).reshape(-1, 3)
    S, O = np.zeros((n, n)), np.zeros((n, n))
    unseeded: list[int] = []
    for i, ref in enumerate(cams):
        X = None
        if pts is not None and len(pts):
            _, _, _, inside = project(ref, pts)
            if inside.sum() >= min_points:
                X = pts[inside]
        if X is None:  # no seeds: around where a converging rig puts its subject, else the whole range
            near, far = ranges[i]
            t = meeting_depth(ref, cams)
            if t is not None and max(near, 0.8 * t) < min(far, 1.25 * t):
                near, far = max(near, 0.8 * t), min(far, 1.25 * t)
            X = sample_view_points(ref, near, far, depths=8)
            unseeded.append(i)
        ri = X - ref.center
        ri /= np.linalg.norm(ri, axis=1, keepdims=True)
        for j, src in enumerate(cams):
            if j == i:
                continue
            _, _, z, inside = project(src, X)
            rj = X - src.center
            rj /= np.linalg.norm(rj, axis=1, keepdims=True) + 1e-12
            deg = np.degrees(np.arccos(np.clip((ri * rj).sum(1), -1, 1)))
            S[i, j] = float(np.mean(inside * _angle_weight(deg)))
            O[i, j] = float(np.mean(inside))
    S[unseeded] = np.where(S[unseeded] < NO_SEED_MIN_SCORE, 0.0, S[unseeded])
    return S, O


def select_sources(scores: np.ndarray, k: int, min_score: float = 0.02) -> list[list[int]]:
    """The k best-scoring source cameras of each reference (those above ``min_score``)."""
    out = []
    for row in scores:
        order = [int(j) for j in np.argsort(-row) if row[j] > min_score]
        out.append(order[:k])
    return out
