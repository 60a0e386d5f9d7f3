"""The space the cameras see, from the cameras alone: depth ranges from the camera layout,
samples in the intersection of the cameras' frusta, and the start points of a scene without any.

Two users, so it sits beside both: atgs-prepare fills the pixels that stereo and SIFT leave
uncovered with such samples, coloured from the images (atgs.data.mvs.fill), and a scene with no
points at all starts from them (:func:`fallback_points`: the model's anchors in
ATGSModel.from_points, the scene bounds in atgs.data.scene). Nothing here reads images or
prepared data, so the model does not depend on data preparation.

Samples lie on rays through a camera's pixels, at depths spread in inverse depth over the
camera's near/far range; a sample is kept if it projects inside at least ``min_views`` cameras
within their own near/far ranges (the intersection of the frusta), and its colour is the mean of
its pixels in those cameras.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from atgs.cameras import Camera
from atgs.geometry.projection import in_image, project
from atgs.geometry.rays import pixel_rays, to_world

SAMPLES_PER_RAY = 16
OVERSAMPLE = 8  # candidate samples per kept point: most samples lie outside the other frusta
FALLBACK_POINTS = 4000  # start points of a scene without any


def median_baseline(cams: Sequence[Camera]) -> float:
    """Median distance between camera centres (1 when they coincide: no scale to take)."""
    c = np.array([x.center for x in cams])
    base = np.linalg.norm(c[:, None] - c[None], axis=-1)
    apart = base > 1e-9 * max(1.0, float(np.abs(c).max()))
    return float(np.median(base[apart])) if apart.any() else 1.0


def axes_meeting_point(cams: Sequence[Camera], min_conditioning: float = 1e-8) -> np.ndarray | None:
    """The point nearest (least squares) to every camera's optical axis: where a rig looks (its
    subject, for rings, domes and arcs); None when the axes are too near parallel for one point
    (the smallest eigenvalue of the normal matrix at most ``min_conditioning`` of the largest)."""
    if len(cams) < 2:
        return None
    A, b = np.zeros((3, 3)), np.zeros(3)
    for cam in cams:
        d = cam.forward / np.linalg.norm(cam.forward)
        P = np.eye(3) - np.outer(d, d)  # distance to the axis through the camera's centre
        A += P
        b += P @ cam.center
    w = np.linalg.eigvalsh(A)
    return np.linalg.solve(A, b) if w[0] > min_conditioning * w[-1] else None


def meeting_depth(cam: Camera, cams: Sequence[Camera]) -> float | None:
    """Depth along ``cam``'s axis of the point where the optical axes of ``cams`` meet (least
    squares), where a converging rig (ring, dome, arc) puts its subject; None for parallel
    front-facing rigs, or when that point is not well in front of ``cam``."""
    p = axes_meeting_point(cams, min_conditioning=0.05)
    if p is None:
        return None
    t = float((p - cam.center) @ cam.forward)
    return t if t > 0.5 * median_baseline(cams) else None


def layout_depth_range(cam: Camera, cams: Sequence[Camera]) -> tuple[float, float]:
    """Near/far of ``cam`` from the camera layout alone (no points): around the distance at which
    the optical axes meet (rings, converging rigs), or many baselines (parallel front-facing rigs)."""
    t = meeting_depth(cam, cams)
    if t is not None:
        return 0.25 * t, 4.0 * t
    baseline = median_baseline(cams)
    return 0.5 * baseline, 200.0 * baseline


def seen_space_samples(cams: Sequence[Camera], ranges: Sequence[tuple[float, float]], points: int,
                       min_views: int, images: Sequence[np.ndarray] | None = None,
                       masks: Sequence[np.ndarray | None] | None = None, seed: int = 0
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``points`` samples (N,3) float64 seen by at least ``min_views`` of ``cams`` within
    their ``ranges`` (near, far), and colours (N,3) float32 in [0,1] (0.5 grey without images).

    ``masks[i]`` (H_i,W_i bool, any resolution) marks the pixels of camera i whose rays may be
    sampled (None: no rays from that camera; ``masks`` None: every pixel of every camera).
    """
    rng = np.random.default_rng(seed)
    n = len(cams)
    if n == 0 or points <= 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.float32)
    masks = [np.ones((1, 1), bool)] * n if masks is None else list(masks)
    active = [i for i in range(n) if masks[i] is not None and masks[i].any()]
    if not active:
        return np.zeros((0, 3)), np.zeros((0, 3), np.float32)
    rays_per_cam = max(1, int(np.ceil(points * OVERSAMPLE / SAMPLES_PER_RAY / len(active))))
    X = np.concatenate([_ray_samples(cams[i], ranges[i], masks[i], rays_per_cam, rng) for i in active])
    count = np.zeros(len(X), np.int64)
    col_sum = np.zeros((len(X), 3))
    for j, cam in enumerate(cams):
        u, v, z, _ = project(cam, X)
        near, far = ranges[j]
        seen = (z >= near) & (z <= far) & in_image(cam, u, v)  # its own depth test: within its near/far range
        count += seen
        if images is not None:
            img = np.asarray(images[j])
            xi = np.clip(u[seen].astype(np.int64), 0, cam.width - 1)
            yi = np.clip(v[seen].astype(np.int64), 0, cam.height - 1)
            col_sum[seen] += img[yi, xi, :3] / 255.0
    keep = count >= min_views
    mean = col_sum / np.maximum(count, 1)[:, None]
    X, mean = X[keep], mean[keep]
    if len(X) > points:
        sel = rng.choice(len(X), points, replace=False)
        X, mean = X[sel], mean[sel]
    colors = mean.astype(np.float32) if images is not None else np.full((len(X), 3), 0.5, np.float32)
    return X, colors


def _ray_samples(cam: Camera, near_far: tuple[float, float], mask: np.ndarray, rays: int,
                 rng: np.random.Generator) -> np.ndarray:
    """World points on ``rays`` random rays through the mask's pixels, SAMPLES_PER_RAY each,
    jittered in inverse depth between near and far."""
    ys, xs = np.nonzero(mask)
    pick = rng.integers(0, len(xs), rays)
    sx, sy = cam.width / mask.shape[1], cam.height / mask.shape[0]
    u = (xs[pick] + rng.random(rays)) * sx
    v = (ys[pick] + rng.random(rays)) * sy
    near, far = near_far
    t = (np.arange(SAMPLES_PER_RAY)[None] + rng.random((rays, SAMPLES_PER_RAY))) / SAMPLES_PER_RAY
    depth = 1.0 / (1.0 / near + t * (1.0 / far - 1.0 / near))  # (rays, S)
    pc = (pixel_rays(cam, u, v)[:, None, :] * depth[..., None]).reshape(-1, 3)
    return to_world(cam, pc)


def fallback_points(cams: Sequence[Camera], num_points: int = FALLBACK_POINTS, seed: int = 0) -> np.ndarray:
    """Points for a scene without any: the space seen by at least two cameras (their depth ranges
    from the camera layout), else by one; no images needed."""
    cams = list(cams)
    ranges = [layout_depth_range(c, cams) for c in cams]
    for views in (2, 1):
        pts, _ = seen_space_samples(cams, ranges, num_points, min(views, len(cams)), seed=seed)
        if len(pts):
            return pts
    return pts
