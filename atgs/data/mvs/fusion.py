"""Cross-view consistency filter and fusion of depth maps into coloured points.

A reference depth is kept only if at least ``min_consistent`` other cameras agree with it: the
reference point, projected into camera j, lands on a pixel whose depth, back-projected and
projected back into the reference, returns within ``reproj_px`` of where it started, with a
depth within ``rel_depth`` of the reference depth (the geometric check of Galliani et al. 2015
and MVSNet). Where fewer other cameras can see the point (it projects into their image, onto a
pixel without a depth or whose depth is not in front of it: nothing occludes it there), every
one of them must agree, and at least one: the edges of a sparse rig, and what one camera sees around an
occluder, are seen by two cameras only. Camera j's depth at the projected point is interpolated bilinearly in inverse depth
(exact on planes) unless the 2x2 pixels around it straddle a depth edge. A kept point is the
mean of the reference point and the agreeing cameras' points, its colour the mean of their
pixels. ``fuse_reference`` is the per-pixel loop the tests compare
the vectorized path with.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from atgs.cameras import Camera, pinhole_pixels
from atgs.data.mvs.config import StereoConfig
from atgs.data.mvs.patchmatch import DepthMap
from atgs.data.mvs.views import View
from atgs.geometry.projection import in_image
from atgs.geometry.rays import pixel_centres, pixel_rays


def _to_world(cam: Camera, pc: torch.Tensor) -> torch.Tensor:
    """Camera-space points (3,M) -> world (3,M)."""
    R, t = torch.from_numpy(cam.R), torch.from_numpy(cam.t)
    return R.T @ (pc - t[:, None])


def _to_camera(cam: Camera, X: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """World points (3,M) -> pixel u, v and depth z."""
    pc = torch.from_numpy(cam.R) @ X + torch.from_numpy(cam.t)[:, None]
    z = pc[2]
    zs = torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))
    return (*pinhole_pixels(cam, pc.T, zs), z)


SMOOTH_SPREAD = 0.1  # 2x2 inverse depths spread less than this (relative): one surface, interpolate


def sample_depth(depth: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Depth (float64) at continuous pixel coordinates: bilinear in inverse depth (exact on planes)
    where the 2x2 pixels around are valid and close (one surface), else the nearest pixel's."""
    h, w = depth.shape
    d = depth.double()
    nearest = d[v.floor().long().clamp(0, h - 1), u.floor().long().clamp(0, w - 1)]
    x, y = u - 0.5, v - 0.5
    x0, y0 = x.floor().long().clamp(0, max(w - 2, 0)), y.floor().long().clamp(0, max(h - 2, 0))
    fx, fy = (x - x0).clamp(0, 1), (y - y0).clamp(0, 1)
    x1, y1 = (x0 + 1).clamp(max=w - 1), (y0 + 1).clamp(max=h - 1)
    q = torch.stack([d[y0, x0], d[y0, x1], d[y1, x0], d[y1, x1]])
    inv = 1.0 / q.clamp_min(1e-12)
    lerp = (inv[0] * (1 - fx) + inv[1] * fx) * (1 - fy) + (inv[2] * (1 - fx) + inv[3] * fx) * fy
    smooth = (q > 0).all(0) & (inv.max(0).values - inv.min(0).values <= SMOOTH_SPREAD * lerp)
    return torch.where(smooth, 1.0 / lerp.clamp_min(1e-12), nearest)


def _sample_depth_reference(depth: np.ndarray, u: float, v: float) -> float:
    h, w = depth.shape
    nearest = float(depth[min(max(int(np.floor(v)), 0), h - 1), min(max(int(np.floor(u)), 0), w - 1)])
    x0 = min(max(int(np.floor(u - 0.5)), 0), max(w - 2, 0))
    y0 = min(max(int(np.floor(v - 0.5)), 0), max(h - 2, 0))
    fx, fy = min(max(u - 0.5 - x0, 0.0), 1.0), min(max(v - 0.5 - y0, 0.0), 1.0)
    q = [float(depth[yy, xx]) for yy in (y0, min(y0 + 1, h - 1)) for xx in (x0, min(x0 + 1, w - 1))]
    if min(q) <= 0:
        return nearest
    inv = [1.0 / z for z in q]
    lerp = (inv[0] * (1 - fx) + inv[1] * fx) * (1 - fy) + (inv[2] * (1 - fx) + inv[3] * fx) * fy
    return 1.0 / lerp if max(inv) - min(inv) <= SMOOTH_SPREAD * lerp else nearest


def fuse_depth_maps(views: Sequence[View], maps: Sequence[DepthMap | None], checks: Sequence[Sequence[int]],
                    cfg: StereoConfig) -> tuple[np.ndarray, np.ndarray]:
    """Consistent points (N,3) float64 and colours (N,3) float32 in [0,1] of all reference cameras.
    ``checks[r]`` lists the cameras whose depth maps may confirm reference r."""
    pts, cols = [], []
    for r, view in enumerate(views):
        if maps[r] is None:
            continue
        cam = view.cam
        depth = maps[r].depth.reshape(-1).double()
        sel = torch.nonzero(depth > 0).reshape(-1)
        if sel.numel() == 0:
            continue
        d = depth[sel]
        X = _to_world(cam, pixel_rays(cam, *pixel_centres(cam), dim=0, inverse_intrinsics=True)[:, sel] * d)
        u0 = (sel % cam.width).double() + 0.5
        v0 = torch.div(sel, cam.width, rounding_mode="floor").double() + 0.5
        count = torch.zeros(sel.numel(), dtype=torch.int64)
        seen = torch.zeros(sel.numel(), dtype=torch.int64)
        sum_x = X.clone()
        sum_c = view.rgb.reshape(-1, 3)[sel].double().clone()
        for j in checks[r]:
            if j == r or maps[j] is None:
                continue
            cj = views[j].cam
            u, v, z = _to_camera(cj, X)
            inside = (z > 0) & in_image(cj, u, v)
            xi = u.floor().long().clamp(0, cj.width - 1)
            yi = v.floor().long().clamp(0, cj.height - 1)
            dj = sample_depth(maps[j].depth, u, v)
            ok = inside & (dj > 0)
            Xj = _to_world(cj, pixel_rays(cj, u, v, dim=0) * dj)
            ur, vr, zr = _to_camera(cam, Xj)
            err = torch.hypot(ur - u0, vr - v0)
            agree = ok & (err < cfg.reproj_px) & ((zr - d).abs() < cfg.rel_depth * d)
            count += agree.long()
            seen += (inside & ((dj <= 0) | (dj > (1 - cfg.rel_depth) * z))).long()  # unless something is in front
            sum_x += Xj * agree
            sum_c += views[j].rgb[yi, xi].double() * agree[:, None]
        keep = count >= torch.clamp(seen, 1, cfg.min_consistent)
        n = (1 + count[keep]).double()
        pts.append((sum_x[:, keep] / n).T.numpy())
        cols.append((sum_c[keep] / n[:, None]).float().numpy())
    if not pts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.float32)
    return np.concatenate(pts), np.concatenate(cols)


def fuse_reference(views: Sequence[View], maps: Sequence[DepthMap | None], checks: Sequence[Sequence[int]],
                   cfg: StereoConfig) -> tuple[np.ndarray, np.ndarray]:
    """The same as :func:`fuse_depth_maps`, one pixel at a time with NumPy and Camera.project."""
    pts, cols = [], []
    for r, view in enumerate(views):
        if maps[r] is None:
            continue
        cam, D = view.cam, maps[r].depth.numpy()
        for y in range(cam.height):
            for x in range(cam.width):
                d = float(D[y, x])
                if d <= 0:
                    continue
                pc = np.linalg.inv(cam.K) @ np.array([x + 0.5, y + 0.5, 1.0]) * d
                X = cam.R.T @ (pc - cam.t)
                acc_x, acc_c = [X], [view.rgb[y, x].numpy().astype(np.float64)]
                seen = 0
                for j in checks[r]:
                    if j == r or maps[j] is None:
                        continue
                    cj = views[j].cam
                    uv, z = cj.project(X[None])
                    u, v = uv[0]
                    if not (z[0] > 0 and 0 <= u < cj.width and 0 <= v < cj.height):
                        continue
                    xi, yi = int(np.floor(u)), int(np.floor(v))
                    dj = _sample_depth_reference(maps[j].depth.numpy(), u, v)
                    seen += dj <= 0 or dj > (1 - cfg.rel_depth) * z[0]
                    if dj <= 0:
                        continue
                    Xj = cj.R.T @ (np.linalg.inv(cj.K) @ np.array([u, v, 1.0]) * dj - cj.t)
                    uvr, zr = cam.project(Xj[None])
                    if np.hypot(*(uvr[0] - [x + 0.5, y + 0.5])) < cfg.reproj_px and abs(zr[0] - d) < cfg.rel_depth * d:
                        acc_x.append(Xj)
                        acc_c.append(views[j].rgb[yi, xi].numpy().astype(np.float64))
                if len(acc_x) - 1 >= min(max(seen, 1), cfg.min_consistent):
                    pts.append(np.mean(acc_x, 0))
                    cols.append(np.mean(acc_c, 0))
    return np.array(pts).reshape(-1, 3), np.array(cols, np.float32).reshape(-1, 3)


def voxel_average(points: np.ndarray, colors: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """One point per occupied voxel: the mean position and colour of the points in it."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if len(points) == 0 or voxel <= 0:
        return points, np.asarray(colors, np.float32).reshape(-1, 3)
    key = np.floor((points - points.min(0)) / voxel).astype(np.int64)
    dims = key.max(0) + 1
    flat = (key[:, 0] * dims[1] + key[:, 1]) * dims[2] + key[:, 2]
    _, inv, cnt = np.unique(flat, return_inverse=True, return_counts=True)
    out_p = np.stack([np.bincount(inv, points[:, k]) for k in range(3)], 1) / cnt[:, None]
    out_c = np.stack([np.bincount(inv, colors[:, k]) for k in range(3)], 1) / cnt[:, None]
    return out_p, out_c.astype(np.float32)


def capped_voxel_average(points: np.ndarray, colors: np.ndarray, voxel: float,
                         max_points: int) -> tuple[np.ndarray, np.ndarray, float]:
    """:func:`voxel_average`, growing the voxel until at most ``max_points`` remain (0: no cap)."""
    p, c = voxel_average(points, colors, voxel)
    while max_points and len(p) > max_points:
        voxel *= max(1.1, float(np.sqrt(len(p) / max_points)))  # surfaces: count ~ 1 / voxel^2
        p, c = voxel_average(points, colors, voxel)
    return p, c, voxel
