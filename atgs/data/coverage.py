"""Coverage: how much of a camera's image the keyframe points explain.

Definition (docs/data.md): the camera is taken at the working resolution (long side at most
``long_side`` pixels, the resolution of the stereo). Every point in front of the camera is
splatted as a disc whose world radius is the point spacing (the median distance from a point to
its nearest neighbour among the same keyframe's points; for voxel-averaged stereo points, about
one voxel), i.e. ``radius_px = f * spacing / z``, at least half a pixel and at most
``MAX_RADIUS_FRAC`` of the long side. A pixel is covered when its center lies within a disc.
Occlusion is ignored (a pixel is covered whichever surface the point belongs to). Coverage of a
camera is the covered fraction of its pixels, averaged over the keyframes.

``coverage_mask`` is the fast path; ``coverage_mask_reference`` the pixel-by-point loop the
tests compare it with.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from atgs.cameras import Camera

DEFAULT_LONG_SIDE = 400
MAX_RADIUS_FRAC = 0.05


def point_spacing(points: np.ndarray, sample: int = 2000, seed: int = 0) -> float:
    """Median nearest-neighbour distance of (a random sample of) the points; 0 for < 2 points."""
    p = torch.from_numpy(np.unique(np.asarray(points, np.float64).reshape(-1, 3), axis=0))
    if p.shape[0] < 2:
        return 0.0
    g = torch.Generator().manual_seed(seed)
    q = p[torch.randperm(p.shape[0], generator=g)[:sample]]
    nn = []
    for i in range(0, q.shape[0], 512):
        d = torch.cdist(q[i:i + 512], p)
        nn.append(d.topk(2, dim=1, largest=False).values[:, 1])  # the first is the point itself
    return float(torch.cat(nn).median())


def _splats(cam: Camera, points: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projected centers u, v and pixel radii of the points in front of ``cam``."""
    uv, z = cam.project(np.asarray(points, np.float64).reshape(-1, 3))
    front = z > 1e-9
    uv, z = uv[front], z[front]
    rmax = MAX_RADIUS_FRAC * max(cam.width, cam.height)
    rad = np.clip(np.sqrt(cam.fx * cam.fy) * spacing / z, 0.5, rmax)
    return uv[:, 0], uv[:, 1], rad


def coverage_mask(cam: Camera, points: np.ndarray, spacing: float) -> np.ndarray:
    """(H,W) bool: pixels of ``cam`` whose center lies within a splatted point's disc."""
    u, v, rad = _splats(cam, points, spacing)
    h, w = cam.height, cam.width
    keep = (u + rad >= 0) & (u - rad <= w) & (v + rad >= 0) & (v - rad <= h)
    u, v, rad = u[keep], v[keep], rad[keep]
    mask = np.zeros(h * w, bool)
    reach = np.ceil(rad).astype(np.int64) + 1
    for k in np.unique(reach):  # points with the same reach share one offset stencil
        sel = reach == k
        off = np.arange(-k, k + 1)
        ox, oy = np.meshgrid(off, off)
        for lo in range(0, int(sel.sum()), 4096):
            uu, vv, rr = (a[sel][lo:lo + 4096, None] for a in (u, v, rad))
            px = np.floor(uu).astype(np.int64) + ox.reshape(1, -1)
            py = np.floor(vv).astype(np.int64) + oy.reshape(1, -1)
            hit = ((px + 0.5 - uu) ** 2 + (py + 0.5 - vv) ** 2 <= rr**2) & (px >= 0) & (px < w) & (py >= 0) & (py < h)
            mask[(py * w + px)[hit]] = True
    return mask.reshape(h, w)


def coverage_mask_reference(cam: Camera, points: np.ndarray, spacing: float) -> np.ndarray:
    """The same mask, every pixel center tested against every disc."""
    u, v, rad = _splats(cam, points, spacing)
    mask = np.zeros((cam.height, cam.width), bool)
    for y in range(cam.height):
        for x in range(cam.width):
            mask[y, x] = bool(np.any((x + 0.5 - u) ** 2 + (y + 0.5 - v) ** 2 <= rad**2))
    return mask


def working_camera(cam: Camera, long_side: int = DEFAULT_LONG_SIDE) -> Camera:
    """``cam`` for its image box-downsampled to at most ``long_side`` pixels (stereo and coverage)."""
    s = min(1.0, float(long_side) / max(cam.width, cam.height))
    return cam if s == 1.0 else cam.scaled(s)


def camera_coverage(cam: Camera, points: np.ndarray, spacing: float | None = None,
                    long_side: int = DEFAULT_LONG_SIDE) -> float:
    """Covered fraction of ``cam``'s pixels at the working resolution (spacing: measured if None)."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return 0.0
    sp = point_spacing(pts) if spacing is None else float(spacing)
    return float(coverage_mask(working_camera(cam, long_side), pts, sp).mean())


def scene_coverage(cameras: Sequence[Camera], points: np.ndarray, point_keyframes: np.ndarray, num_keyframes: int,
                   test_cameras: Sequence[str] = (), long_side: int = DEFAULT_LONG_SIDE) -> dict:
    """Coverage of every camera by each keyframe's points (spacing measured per keyframe),
    averaged over the keyframes: ``{"per_camera": {name: c}, "mean": mean over training cameras,
    "test_cameras": {name: c}, "long_side": ...}``."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    kf = np.asarray(point_keyframes).reshape(-1)
    per = {c.name: 0.0 for c in cameras}
    for j in range(num_keyframes):
        p = pts[kf == j]
        if len(p) == 0:
            continue
        sp = point_spacing(p)
        for c in cameras:
            per[c.name] += camera_coverage(c, p, sp, long_side) / num_keyframes
    per = {k: round(v, 4) for k, v in per.items()}
    test = set(test_cameras)
    train = [v for k, v in per.items() if k not in test]
    return {"per_camera": per, "mean": round(float(np.mean(train)) if train else 0.0, 4),
            "test_cameras": {k: per[k] for k in per if k in test}, "long_side": int(long_side)}
