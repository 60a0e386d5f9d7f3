"""The fallback start: points in the space seen by at least two cameras.

Where stereo and SIFT leave a camera's pixels uncovered (textureless surfaces, very wide
baselines, two to four cameras), rays through those pixels are sampled at depths spread in
inverse depth over the camera's near/far range. A sample is kept if it projects inside at least
``min_views`` cameras within their own near/far ranges (the intersection of the frusta); its
colour is the mean of its pixels in those cameras. Training then starts from these points and
densification grows and prunes from there.

Image consistency (space carving: keep the samples whose colours agree across the cameras) was
tried and dropped: on a textured test scene it did not bring the fill closer to the surfaces
(docs/data.md), because depth samples sparse enough to be affordable rarely land within a
pixel's footprint of the surface.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from atgs.cameras import Camera
from atgs.data.mvs.config import FillConfig

SAMPLES_PER_RAY = 16
OVERSAMPLE = 8  # candidate samples per kept point: most samples lie outside the other frusta


def frustum_fill(cams: Sequence[Camera], ranges: Sequence[tuple[float, float]], cfg: FillConfig = FillConfig(),
                 images: Sequence[np.ndarray] | None = None, masks: Sequence[np.ndarray | None] | None = None,
                 seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Fill points (N,3) float64 and colours (N,3) float32 in [0,1] (0.5 grey without images).

    ``masks[i]`` (H_i,W_i bool, any resolution) marks the pixels of camera i whose rays may be
    sampled (None: no rays from that camera; ``masks`` None: every pixel of every camera).
    """
    rng = np.random.default_rng(seed)
    n = len(cams)
    if n == 0 or cfg.points <= 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.float32)
    masks = [np.ones((1, 1), bool)] * n if masks is None else list(masks)
    active = [i for i in range(n) if masks[i] is not None and masks[i].any()]
    if not active:
        return np.zeros((0, 3)), np.zeros((0, 3), np.float32)
    rays_per_cam = max(1, int(np.ceil(cfg.points * OVERSAMPLE / SAMPLES_PER_RAY / len(active))))
    X = np.concatenate([_ray_samples(cams[i], ranges[i], masks[i], rays_per_cam, rng) for i in active])
    count = np.zeros(len(X), np.int64)
    col_sum = np.zeros((len(X), 3))
    for j, cam in enumerate(cams):
        uv, z = cam.project(X)
        near, far = ranges[j]
        with np.errstate(invalid="ignore"):
            seen = (z >= near) & (z <= far) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        count += seen
        if images is not None:
            img = np.asarray(images[j])
            xi = np.clip(uv[seen, 0].astype(np.int64), 0, cam.width - 1)
            yi = np.clip(uv[seen, 1].astype(np.int64), 0, cam.height - 1)
            col_sum[seen] += img[yi, xi, :3] / 255.0
    keep = count >= cfg.min_views
    mean = col_sum / np.maximum(count, 1)[:, None]
    X, mean = X[keep], mean[keep]
    if len(X) > cfg.points:
        sel = rng.choice(len(X), cfg.points, replace=False)
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
    dirs = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones(rays)], 1)
    pc = (dirs[:, None, :] * depth[..., None]).reshape(-1, 3)
    return (pc - cam.t) @ cam.R


def fallback_points(cams: Sequence[Camera], num_points: int = 4000, seed: int = 0) -> np.ndarray:
    """Points for a scene without any: the space seen by at least two cameras (their depth ranges
    from the camera layout), else by one; grey, no images needed (the trainer's last resort)."""
    from atgs.data.mvs.views import layout_depth_range

    cams = list(cams)
    ranges = [layout_depth_range(c, cams) for c in cams]
    for views in (2, 1):
        pts, _ = frustum_fill(cams, ranges, FillConfig(points=num_points, min_views=min(views, len(cams))), seed=seed)
        if len(pts):
            return pts
    return pts
