"""Extend measured surfaces into the pixels that stereo and SIFT left uncovered.

Dense stereo leaves gaps where few cameras see a surface: the top of a backdrop seen only by the
lower cameras, regions at the image border, grazing walls. Training grows anchors only near
existing ones, so a gap wider than a few anchors stays empty (black, or smeared by far-away
Gaussians) in every view that sees it. For each training camera, the uncovered pixels within
``reach`` of covered ones get points at the depth of the nearest covered pixels (a depth map
splatted from the measured points and grown outwards ring by ring), coloured from the image.
These points are a starting guess, not a measurement: they are placed on the camera's own rays,
so they render where that camera sees the content, and training moves, grows or prunes them.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from atgs.cameras import Camera
from atgs.geometry.coverage import NEAR, coverage_mask, working_camera
from atgs.geometry.projection import project
from atgs.geometry.rays import pixel_rays, to_world


def depth_map(cam: Camera, points: np.ndarray) -> np.ndarray:
    """(H, W) nearest depth of the points projecting into each pixel of ``cam``; NaN elsewhere."""
    u, v, z, ok = project(cam, points, near=NEAR)
    depth = np.full(cam.height * cam.width, np.inf)
    idx = v[ok].astype(np.int64) * cam.width + u[ok].astype(np.int64)
    np.minimum.at(depth, idx, z[ok])
    depth[np.isinf(depth)] = np.nan
    return depth.reshape(cam.height, cam.width)


def grow_depth(depth: np.ndarray, steps: int) -> np.ndarray:
    """Fill NaN pixels from their 4-neighbours, one ring per step (the mean of the neighbours
    known at that step), ``steps`` rings at most."""
    d = depth.copy()
    for _ in range(max(0, int(steps))):
        missing = np.isnan(d)
        if not missing.any():
            break
        total = np.zeros_like(d)
        count = np.zeros_like(d)
        known = np.where(missing, 0.0, d)
        has = (~missing).astype(d.dtype)
        for axis, shift in ((0, 1), (0, -1), (1, 1), (1, -1)):
            total += _shifted(known, axis, shift)
            count += _shifted(has, axis, shift)
        new = missing & (count > 0)
        if not new.any():
            break
        d[new] = total[new] / count[new]
    return d


def _shifted(a: np.ndarray, axis: int, shift: int) -> np.ndarray:
    """``a`` moved by ``shift`` along ``axis``, zero-filled (no wrap-around)."""
    out = np.zeros_like(a)
    src = [slice(None)] * 2
    dst = [slice(None)] * 2
    if shift > 0:
        src[axis], dst[axis] = slice(0, -shift), slice(shift, None)
    else:
        src[axis], dst[axis] = slice(-shift, None), slice(0, shift)
    out[tuple(dst)] = a[tuple(src)]
    return out


def extend_surfaces(cams: Sequence[Camera], images: Sequence[np.ndarray], points: np.ndarray, spacing: float,
                    long_side: int, reach: float, max_points: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points (N,3) float64 and colours (N,3) float32 in [0,1] on the uncovered pixels of each
    camera that lie within ``reach`` (a fraction of the working image's long side) of covered
    ones, one per ``stride`` working pixels (the points' own spacing in that view), at most
    ``max_points`` in all."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if len(pts) < 2 or spacing <= 0 or reach <= 0 or max_points <= 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.float32)
    out_p, out_c = [], []
    for cam, img in zip(cams, images):
        wc = working_camera(cam, long_side)
        covered = coverage_mask(wc, pts, spacing)
        if covered.all():
            continue
        steps = int(np.ceil(reach * max(wc.width, wc.height)))
        depth = grow_depth(depth_map(wc, pts), steps + _gap(wc, pts, spacing))
        z_med = np.nanmedian(depth) if np.isfinite(depth).any() else np.nan
        if not np.isfinite(z_med):
            continue
        # one point per point-spacing in this view, as the measured points are spread
        stride = max(1, int(round(np.sqrt(wc.fx * wc.fy) * spacing / z_med)))
        grid = np.zeros_like(covered)
        grid[stride // 2::stride, stride // 2::stride] = True
        ys, xs = np.nonzero(grid & ~covered & np.isfinite(depth))
        if len(xs) == 0:
            continue
        z = depth[ys, xs]
        u, v = xs + 0.5, ys + 0.5
        out_p.append(to_world(wc, pixel_rays(wc, u, v) * z[:, None]))
        im = np.asarray(img)
        sx, sy = im.shape[1] / wc.width, im.shape[0] / wc.height
        out_c.append(im[np.minimum((v * sy).astype(np.int64), im.shape[0] - 1),
                        np.minimum((u * sx).astype(np.int64), im.shape[1] - 1), :3].astype(np.float32) / 255.0)
    if not out_p:
        return np.zeros((0, 3)), np.zeros((0, 3), np.float32)
    P, C = np.concatenate(out_p), np.concatenate(out_c)
    if len(P) > max_points:
        keep = np.random.default_rng(seed).choice(len(P), max_points, replace=False)
        P, C = P[keep], C[keep]
    return P, C


def _gap(cam: Camera, points: np.ndarray, spacing: float) -> int:
    """Rings needed to close the gaps between splatted points (their spacing in pixels)."""
    _, z = cam.project(points)
    z = z[z > NEAR]
    if len(z) == 0:
        return 0
    return int(np.ceil(np.sqrt(cam.fx * cam.fy) * spacing / float(np.median(z))))
