"""Coverage: how much of a camera's image the keyframe points explain, and by how many cameras.

Definition (docs/data.md): the camera is taken at the working resolution (long side at most
``long_side`` pixels, the resolution of the stereo). Every point in front of the camera is
splatted as a disc whose world radius is the point spacing (the median distance from a point to
its nearest neighbour among the same keyframe's points; for voxel-averaged stereo points, about
one voxel), i.e. ``radius_px = f * spacing / z``, at least half a pixel and at most
``MAX_RADIUS_FRAC`` of the long side. A pixel is covered when its center lies within a disc.
Occlusion is ignored (a pixel is covered whichever surface the point belongs to). Coverage of a
camera is the covered fraction of its pixels, averaged over the keyframes.

Views per measured pixel: a covered pixel shows the nearest point whose disc holds its center,
and takes the number of *training* cameras that see that point. A camera sees a point when the
point projects inside its image, in front of it, and its depth is at most ``DEPTH_TOL`` (5 %)
beyond the nearest point's depth at its pixel of a coarse z-buffer of the same keyframe's points:
the camera at long side ``ZBUFFER_LONG_SIDE`` px, every point splatted as its disc (at least
``ZBUFFER_MIN_RADIUS`` px, so that it always reaches the pixel it falls in). The coarse grid
closes the gaps between the points of a nearer surface, which would let the points behind it look
visible; too coarse a grid hides slanted surfaces behind their own nearer part (80 px: docs/data.md).
A training camera always counts itself on its own pixels (a pixel seen by no other camera has 1);
a test camera does not. A camera's figure is the mean over its covered pixels of all keyframes;
the scene's is the mean over all covered pixels of the training cameras (weighted by covered
pixels: a camera that sees few points weighs little).

``coverage_mask`` and ``views_per_pixel`` are the fast paths; ``coverage_mask_reference`` and
``views_per_pixel_reference`` the pixel-by-point loops the tests compare them with.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np
import torch

from atgs.cameras import Camera
from atgs.geometry.projection import project

DEFAULT_LONG_SIDE = 400
MAX_RADIUS_FRAC = 0.05
ZBUFFER_LONG_SIDE = 80
ZBUFFER_MIN_RADIUS = 0.75  # > sqrt(0.5): a disc always holds the center of the pixel its point falls in
DEPTH_TOL = 0.05  # relative: a point this much beyond the z-buffer is hidden
NEAR = 1e-9  # in front of a camera: the discs' radii divide by the depth


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


def _splats(cam: Camera, points: np.ndarray, spacing: float,
            min_radius: float = 0.5) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Indices, projected centers u, v, pixel radii and depths of the points in front of ``cam``."""
    uv, z = cam.project(np.asarray(points, np.float64).reshape(-1, 3))
    idx = np.nonzero(z > NEAR)[0]
    uv, z = uv[idx], z[idx]
    rmax = MAX_RADIUS_FRAC * max(cam.width, cam.height)
    rad = np.clip(np.sqrt(cam.fx * cam.fy) * spacing / z, min_radius, rmax)
    return idx, uv[:, 0], uv[:, 1], rad, z


def _disc_hits(u: np.ndarray, v: np.ndarray, rad: np.ndarray, w: int,
               h: int) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(disc, pixel) index pairs, in chunks: the pixel centers of a w x h image within each disc."""
    reach = np.ceil(rad).astype(np.int64) + 1
    for k in np.unique(reach):  # discs with the same reach share one offset stencil
        sel = np.nonzero(reach == k)[0]
        off = np.arange(-k, k + 1)
        ox, oy = (a.reshape(1, -1) for a in np.meshgrid(off, off))
        for lo in range(0, len(sel), 4096):
            s = sel[lo:lo + 4096]
            uu, vv, rr = u[s, None], v[s, None], rad[s, None]
            px, py = np.floor(uu).astype(np.int64) + ox, np.floor(vv).astype(np.int64) + oy
            hit = ((px + 0.5 - uu) ** 2 + (py + 0.5 - vv) ** 2 <= rr**2) & (px >= 0) & (px < w) & (py >= 0) & (py < h)
            yield np.broadcast_to(s[:, None], hit.shape)[hit], (py * w + px)[hit]


def front_points(cam: Camera, points: np.ndarray, spacing: float, min_radius: float = 0.5) -> np.ndarray:
    """(H,W) int64: the index of the nearest point whose disc holds the pixel center, -1 where none."""
    idx, u, v, rad, z = _splats(cam, points, spacing, min_radius)
    h, w = cam.height, cam.width
    keep = (u + rad >= 0) & (u - rad <= w) & (v + rad >= 0) & (v - rad <= h)
    order = np.argsort(z[keep], kind="stable")  # depth rank (ties: lower index): the nearest is the min rank
    idx, u, v, rad = (a[keep][order] for a in (idx, u, v, rad))
    n = len(idx)
    best = torch.full((h * w,), n, dtype=torch.int64)
    for rank, pix in _disc_hits(u, v, rad, w, h):
        best.scatter_reduce_(0, torch.from_numpy(pix), torch.from_numpy(np.ascontiguousarray(rank)), "amin")
    best = best.numpy()
    return np.where(best < n, np.append(idx, -1)[best], -1).reshape(h, w)


def coverage_mask(cam: Camera, points: np.ndarray, spacing: float) -> np.ndarray:
    """(H,W) bool: pixels of ``cam`` whose center lies within a splatted point's disc."""
    return front_points(cam, points, spacing) >= 0


def coverage_mask_reference(cam: Camera, points: np.ndarray, spacing: float) -> np.ndarray:
    """The same mask, every pixel center tested against every disc."""
    _, u, v, rad, _ = _splats(cam, points, spacing)
    mask = np.zeros((cam.height, cam.width), bool)
    for y in range(cam.height):
        for x in range(cam.width):
            mask[y, x] = bool(np.any((x + 0.5 - u) ** 2 + (y + 0.5 - v) ** 2 <= rad**2))
    return mask


def working_camera(cam: Camera, long_side: int = DEFAULT_LONG_SIDE) -> Camera:
    """``cam`` for its image box-downsampled to at most ``long_side`` pixels (stereo and coverage)."""
    s = min(1.0, float(long_side) / max(cam.width, cam.height))
    return cam if s == 1.0 else cam.scaled(s)


def seen_by(cams: Sequence[Camera], points: np.ndarray, spacing: float) -> np.ndarray:
    """(C,P) bool: camera c sees point p (inside, in front, not behind the coarse z-buffer)."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    seen = np.zeros((len(cams), len(pts)), bool)
    for ci, cam in enumerate(cams):
        c = working_camera(cam, ZBUFFER_LONG_SIDE)
        front = front_points(c, pts, spacing, ZBUFFER_MIN_RADIUS)
        u, v, z, inside = project(c, pts, near=NEAR)
        i = np.nonzero(inside)[0]
        f = front[np.floor(v[i]).astype(np.int64), np.floor(u[i]).astype(np.int64)]
        seen[ci, i] = (f < 0) | (z[i] <= (1 + DEPTH_TOL) * z[f])
    return seen


def views_per_pixel(cams: Sequence[Camera], points: np.ndarray, spacing: float, test: Sequence[str] = (),
                    long_side: int = DEFAULT_LONG_SIDE) -> list[np.ndarray]:
    """Per camera, an (H,W) int64 map at the working resolution: the number of training cameras
    that see the point a covered pixel shows (module docstring), -1 where no disc covers it."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    train = [i for i, c in enumerate(cams) if c.name not in test]
    seen = seen_by([cams[i] for i in train], pts, spacing)
    n = seen.sum(0)
    maps = []
    for ci, cam in enumerate(cams):
        front = front_points(working_camera(cam, long_side), pts, spacing)
        m = np.full(front.shape, -1, np.int64)
        p = front[front >= 0]
        own = seen[train.index(ci), p] if ci in train else np.ones(len(p), bool)  # a training camera counts itself
        m[front >= 0] = n[p] + ~own
        maps.append(m)
    return maps


def views_per_pixel_reference(cams: Sequence[Camera], points: np.ndarray, spacing: float, test: Sequence[str] = (),
                              long_side: int = DEFAULT_LONG_SIDE) -> list[np.ndarray]:
    """The same maps, every pixel center tested against every disc, point by point."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)

    def nearest_maps(cam: Camera, min_radius: float) -> np.ndarray:
        idx, u, v, rad, z = _splats(cam, pts, spacing, min_radius)
        out = np.full((cam.height, cam.width), -1, np.int64)
        for y in range(cam.height):
            for x in range(cam.width):
                hit = np.nonzero((x + 0.5 - u) ** 2 + (y + 0.5 - v) ** 2 <= rad**2)[0]
                if len(hit):
                    out[y, x] = idx[hit[np.argmin(z[hit])]]
        return out

    train = [c for c in cams if c.name not in test]
    seen = np.zeros((len(train), len(pts)), bool)
    for ci, cam in enumerate(train):
        c = working_camera(cam, ZBUFFER_LONG_SIDE)
        front = nearest_maps(c, ZBUFFER_MIN_RADIUS)
        u, v, z, inside = project(c, pts, near=NEAR)
        for p in np.nonzero(inside)[0]:
            q = front[int(v[p]), int(u[p])]
            seen[ci, p] = q < 0 or z[p] <= (1 + DEPTH_TOL) * z[q]
    maps = []
    for cam in cams:
        front = nearest_maps(working_camera(cam, long_side), 0.5)
        m = np.full(front.shape, -1, np.int64)
        for y, x in zip(*np.nonzero(front >= 0)):
            m[y, x] = sum(bool(s[front[y, x]]) or t.name == cam.name for s, t in zip(seen, train))
        maps.append(m)
    return maps


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
    averaged over the keyframes, and the training cameras per measured pixel (module docstring):
    ``{"per_camera": {name: c}, "mean": mean over training cameras, "test_cameras": {name: c},
    "long_side": ..., "views_per_pixel": {"per_camera": {name: v}, "mean": over the training
    cameras' covered pixels, "test_cameras": {name: v}, "zbuffer_long_side", "depth_tol"}}``;
    a camera without a covered pixel has 0 views."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    kf = np.asarray(point_keyframes).reshape(-1)
    per = {c.name: 0.0 for c in cameras}
    views = {c.name: np.zeros(2) for c in cameras}  # [sum of the counts, covered pixels] over the keyframes
    for j in range(num_keyframes):
        p = pts[kf == j]
        if len(p) == 0:
            continue
        for c, m in zip(cameras, views_per_pixel(cameras, p, point_spacing(p), test_cameras, long_side)):
            per[c.name] += float((m >= 0).mean()) / num_keyframes
            views[c.name] += [m[m >= 0].sum(), (m >= 0).sum()]
    per = {k: round(v, 4) for k, v in per.items()}
    test = set(test_cameras)
    train = [k for k in per if k not in test]
    pooled = sum((views[k] for k in train), np.zeros(2))
    cov = _split(per, test, float(np.mean([per[k] for k in train])) if train else 0.0)
    vpp = _split({k: s / max(n, 1) for k, (s, n) in views.items()}, test, pooled[0] / max(pooled[1], 1))
    return {**cov, "long_side": int(long_side),
            "views_per_pixel": {**vpp, "zbuffer_long_side": ZBUFFER_LONG_SIDE, "depth_tol": DEPTH_TOL}}


def _split(per: dict, test: set, mean: float) -> dict:
    """``{"per_camera": per, "mean": mean, "test_cameras": the test cameras' part}``, rounded for scene.json."""
    per = {k: round(float(v), 4) for k, v in per.items()}
    return {"per_camera": per, "mean": round(float(mean), 4), "test_cameras": {k: per[k] for k in per if k in test}}
