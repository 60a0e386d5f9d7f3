"""Points on moving content at many keyframes, cheaply: motion masks and their visual hull.

Dense stereo costs ~20 s per keyframe (12 cameras at 256x192), so ``atgs-prepare`` runs it at a
few keyframes; moving objects need anchors where they are at many more (docs/training.md,
``bench/moving.py``). The cameras of a multi-view video stand still, so what moves is what
differs from each camera's background, the per-pixel temporal median of its frames. At each
motion keyframe:

1. a motion mask per training camera: channel-mean |frame - background| (3x3 box-blurred) above
   a threshold set from the noise floor (a low percentile of that difference over the pixels),
   opened with a 3x3 window so that isolated noisy pixels do not count; a camera with the
   capture's foreground masks uses those instead (the others keep the difference);
2. the visual hull of the masks: voxels of the scene box inside the images of at least
   ``min_view_fraction`` of the cameras, in the masks of at least ``min_views`` of them and of
   all but ``slack`` of the cameras whose image holds them (a static occluder hides a moving
   object from a camera or two). A voxel's test uses masks
   dilated by its projected radius, so a coarse voxel is kept when any part of it may be inside;
   the kept coarse voxels are then subdivided, and a fine voxel is kept when its centre is inside;
3. along each masked pixel's ray, the hull voxel whose colour nearby cameras agree on best
   becomes a point (``select="photo"``; :func:`photo_consistent`), or the hull's surface voxels
   do (``select="surface"``, also the fallback where no two nearby views agree), coloured with
   the median of their pixels over the cameras whose masks hold them, at most ``max_points``.

A static scene gives empty masks and no points. Everything is deterministic.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Annotated, Literal

import numpy as np
import torch
import torch.nn.functional as F
import tyro

from atgs.cameras import Camera, pinhole_pixels, to_camera_frame
from atgs.data.motion_measure import box_downsample, frame_difference
from atgs.timeline import evenly_spaced


@dataclass(frozen=True)
class MotionPointsConfig:
    """Knobs of the moving-content points (``atgs-prepare --motion.*``)."""

    enabled: Annotated[bool, tyro.conf.arg(name="motion-points", prefix_name=False)] = True
    """Points on moving content at extra keyframes, from motion masks (--no-motion-points: off)."""
    per_interval: int = 8
    """Motion keyframes per interval between two geometry keyframes (8: K geometry keyframes give
    8 (K - 1) + 1 motion keyframes, the geometry ones among them). On the built-in scene at
    20 minutes, 2 / 4 / 8 scored 24.55 / 25.05 / 25.25 dB held out (docs/training.md)."""
    long_side: int = 200
    """Working resolution of the masks (long side, pixels)."""
    background_frames: int = 48
    """Evenly spaced frames per camera whose median is the background."""
    noise_multiplier: float = 6.0
    """Threshold in noise floors (the 25th percentile of the difference over the pixels)."""
    min_threshold: float = 12.0 / 255.0
    """Never count smaller changes (lossy video drifts by up to ~12/255, docs/auto.md)."""
    max_threshold: float = 0.15
    """Never ask for larger changes (a noisy, ever-moving frame must not hide strong ones)."""
    min_views: int = 3
    """A hull voxel is inside the masks of at least this many cameras."""
    slack: int = 1
    """... and of all but this many of the cameras whose image holds it."""
    min_view_fraction: float = 0.5
    """... and lies inside the images of at least this share of the cameras: space that few cameras
    see is where the hull's phantoms are (built-in scene: voxels seen by 3-6 of 11 cameras were
    all phantoms, those seen by all 11 were 91% within 0.3 m of a moving surface)."""
    resolution: int = 64
    """Coarse voxels along the longest side of the scene box."""
    subdivide: int = 4
    """Each kept coarse voxel is split into subdivide^3 fine ones."""
    max_points: int = 3000
    """Per keyframe (a deterministic subsample beyond)."""
    min_points: int = 8
    """A keyframe with fewer hull points gets none (noise, not an object)."""
    select: Literal["photo", "surface"] = "photo"
    """Which hull voxels become points: "photo" (per masked pixel ray, the voxel whose colour the
    nearby cameras agree on best) or "surface" (the hull's surface voxels)."""

    def validate(self) -> None:
        if self.per_interval < 1:
            raise ValueError(f"--motion.per-interval {self.per_interval}: must be >= 1")
        if self.min_views < 2:
            raise ValueError(f"--motion.min-views {self.min_views}: must be >= 2 (one view has no depth)")
        if self.select not in ("photo", "surface"):
            raise ValueError(f"--motion.select {self.select!r}: choose photo or surface")
        if self.resolution < 4 or self.subdivide < 1 or self.long_side < 16:
            raise ValueError("--motion.resolution >= 4, --motion.subdivide >= 1, --motion.long-side >= 16")


@dataclass
class MotionPoints:
    keyframes: list[int]  # frame indices, ascending (empty: nothing moves)
    points: np.ndarray  # (P,3) float64
    colors: np.ndarray  # (P,3) float32 in [0,1]
    point_keyframes: np.ndarray  # (P,) int64, index into ``keyframes``
    stats: dict = field(default_factory=dict)  # for scene.json

    def scene_fields(self) -> dict:
        """These points as the motion fields of an :class:`atgs.data.scene.MemoryScene`."""
        return {"motion_keyframes": list(self.keyframes), "motion_points": self.points,
                "motion_point_colors": self.colors, "motion_point_keyframes": self.point_keyframes}


def motion_keyframes(num_frames: int, geometry_keyframes: int, per_interval: int) -> list[int]:
    """(K - 1) * per_interval + 1 evenly spaced frames: a superset of the K geometry keyframes
    (evenly_spaced is exact, so j * per_interval maps onto geometry keyframe j)."""
    return evenly_spaced(num_frames, max(1, geometry_keyframes - 1) * per_interval + 1)


# --- pieces (pure functions, tested on their own) -----------------------------------------------

def background(frames: Sequence[np.ndarray]) -> np.ndarray:
    """Per-pixel temporal median of channel-first float frames (C,H,W) -> (C,H,W)."""
    return np.median(np.stack(frames), axis=0).astype(np.float32)


def motion_mask(frame: np.ndarray, bg: np.ndarray, cfg: MotionPointsConfig) -> np.ndarray:
    """(H,W) bool: pixels of ``frame`` (C,H,W) that differ from the background ``bg``."""
    d = torch.from_numpy(frame_difference(frame, bg))[None, None]
    d = F.avg_pool2d(d, 3, 1, 1, count_include_pad=False)
    noise = float(torch.quantile(d.flatten(), 0.25))
    thr = min(max(cfg.noise_multiplier * noise, cfg.min_threshold), cfg.max_threshold)
    m = (d > thr).float()
    m = -F.max_pool2d(-m, 3, 1, 1)  # erode
    m = F.max_pool2d(m, 3, 1, 1)  # dilate back: an opening
    return m[0, 0].numpy() > 0.5


def foreground_mask(mask: np.ndarray, long_side: int) -> np.ndarray:
    """A capture's foreground mask (H,W bool) at the masks' working resolution: the frames' box
    downsampling (:func:`box_downsample`), foreground where at least half the block is."""
    return box_downsample(np.asarray(mask, bool).astype(np.uint8)[..., None] * 255, long_side)[0] >= 0.5


def _dilations(mask: np.ndarray, max_radius: int) -> list[torch.Tensor]:
    """Masks dilated by 0, 1, 2, 4, ... pixels (square windows), up to ``max_radius``."""
    m = torch.from_numpy(mask.astype(np.float32))[None, None]
    out, r = [m[0, 0] > 0], 1
    while r <= max_radius:
        out.append(F.max_pool2d(m, 2 * r + 1, 1, r)[0, 0] > 0)
        r *= 2
    return out


def hull_votes(centers: np.ndarray, half_size: float, cams: Sequence[Camera], masks: Sequence[np.ndarray],
               min_views: int, slack: int, min_see: int = 0, dilate: bool = True) -> np.ndarray:
    """(N,) bool: voxels (centres, half edge) inside the visual hull of ``masks`` (one per camera,
    any resolution): whose centre is inside the images of >= ``min_see`` cameras, in the masks
    (dilated by the voxel's projected radius) of >= ``min_views`` of them and of all but ``slack``."""
    x = torch.from_numpy(np.asarray(centers, np.float64))
    n_in = torch.zeros(len(x), dtype=torch.int32)
    n_see = torch.zeros(len(x), dtype=torch.int32)
    radius_world = half_size * math.sqrt(3.0)
    for cam, mask in zip(cams, masks):
        pc = to_camera_frame(cam, x)
        z = pc[:, 2]
        front = z > 1e-6
        zs = torch.where(front, z, torch.ones_like(z))
        u, v = pinhole_pixels(cam, pc, zs)
        H, W = mask.shape
        sx, sy = W / cam.width, H / cam.height  # the mask may be downsampled
        ui, vi = torch.floor(u * sx).long(), torch.floor(v * sy).long()
        inside = front & (ui >= 0) & (ui < W) & (vi >= 0) & (vi < H)
        r_px = cam.fx * sx * radius_world / zs if dilate else torch.zeros_like(zs)
        levels = _dilations(mask, int(min(max(H, W), math.ceil(float(r_px[inside].max()) if inside.any() else 0))))
        # level l dilates by 0 (l = 0) or 2^(l-1) pixels: the smallest that covers the radius
        lvl = torch.where(r_px <= 0.5, 0, torch.ceil(torch.log2(r_px.clamp_min(1.0))).long() + 1)
        lvl = lvl.clamp(0, len(levels) - 1)
        hit = torch.zeros(len(x), dtype=torch.bool)
        idx = torch.nonzero(inside).flatten()
        if len(idx):
            stack = torch.stack(levels)  # (L,H,W)
            hit[idx] = stack[lvl[idx], vi[idx], ui[idx]]
        n_see += inside.int()
        n_in += hit.int()
    return (n_see >= min_see) & (n_in >= min_views) & (n_in >= n_see - slack)


def visual_hull(cams: Sequence[Camera], masks: Sequence[np.ndarray], box: np.ndarray, cfg: MotionPointsConfig
                ) -> tuple[np.ndarray, np.ndarray, float]:
    """Centres of the fine voxels of the hull, which of them are on its surface, and the fine
    voxel edge."""
    lo, hi = np.asarray(box, np.float64)
    size = float(np.max(hi - lo)) / cfg.resolution
    dims = np.maximum(1, np.ceil((hi - lo) / size).astype(int))
    grid = np.stack(np.meshgrid(*[np.arange(d) for d in dims], indexing="ij"), -1).reshape(-1, 3)
    centers = lo + (grid + 0.5) * size
    min_see = math.ceil(cfg.min_view_fraction * len(cams))
    keep = hull_votes(centers, size / 2, cams, masks, cfg.min_views, cfg.slack, min_see).numpy()
    coarse = grid[keep]
    s = cfg.subdivide
    fine_size = size / s
    if len(coarse) == 0:
        return np.zeros((0, 3)), np.zeros(0, bool), fine_size
    sub = np.stack(np.meshgrid(*[np.arange(s)] * 3, indexing="ij"), -1).reshape(-1, 3)
    fine = (coarse[:, None, :] * s + sub[None]).reshape(-1, 3)
    fcent = lo + (fine + 0.5) * fine_size
    # fine voxels: the centre's pixel decides (a dilated test would pad the hull by a voxel or two)
    fkeep = hull_votes(fcent, fine_size / 2, cams, masks, cfg.min_views, cfg.slack, min_see, dilate=False).numpy()
    fine = fine[fkeep]
    return lo + (fine + 0.5) * fine_size, _surface(fine), fine_size


def _masked_pixels(points: np.ndarray, cam: Camera, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which points land in ``cam``'s mask (any resolution), and their pixel columns and rows."""
    uv, z = cam.project(points)
    H, W = mask.shape
    u = np.floor(uv[:, 0] * W / cam.width).astype(np.int64)
    v = np.floor(uv[:, 1] * H / cam.height).astype(np.int64)
    ok = (z > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    ok[ok] &= mask[v[ok], u[ok]]
    return ok, u, v


def photo_consistent(points: np.ndarray, cams: Sequence[Camera], masks: Sequence[np.ndarray],
                     images: Sequence[np.ndarray], max_angle_deg: float = 60.0) -> np.ndarray:
    """(N,) bool: along each masked pixel's ray of each camera, the voxel whose colour agrees best
    with the cameras that see it from within ``max_angle_deg`` (or 1.5x the median angle between
    neighbouring cameras where that is wider; variance over them, at least two views). A hull
    seen from close-by cameras (a front-facing rig) is deep along the view direction; this picks the depth where the views agree, as stereo does. ``images`` are
    channel-first (C,H,W) at the masks' resolution."""
    n = len(points)
    x = torch.from_numpy(np.asarray(points, np.float64))
    cols, valid, dirs, pix = [], [], [], []
    for cam, mask, img in zip(cams, masks, images):
        ok, u, v = _masked_pixels(points, cam, mask)
        W = mask.shape[1]
        c = np.zeros((n, 3), np.float32)
        c[ok] = img[:, v[ok], u[ok]].T
        cols.append(torch.from_numpy(c))
        valid.append(torch.from_numpy(ok))
        d = x - torch.from_numpy(cam.center)
        dirs.append(d / d.norm(dim=1, keepdim=True).clamp_min(1e-12))
        pix.append(torch.from_numpy(np.where(ok, v * W + u, -1)))
    cols_t, valid_t, dirs_t = torch.stack(cols), torch.stack(valid), torch.stack(dirs)  # (C,N,3), (C,N), (C,N,3)
    # sparse rigs: widen the cone to 1.5x the typical angle between neighbouring cameras, so that
    # every camera has a neighbour to agree with
    cen = torch.stack([torch.from_numpy(c.center) for c in cams]) - x.mean(0)
    cen = cen / cen.norm(dim=1, keepdim=True).clamp_min(1e-12)
    ang = torch.rad2deg(torch.acos((cen @ cen.T).clamp(-1, 1))) + torch.eye(len(cams)) * 360
    spread = float(ang.min(1).values.median()) if len(cams) > 1 else 0.0
    cos_max = math.cos(math.radians(min(180.0, max(max_angle_deg, 1.5 * spread))))
    chosen = torch.zeros(n, dtype=torch.bool)
    for i in range(len(cams)):
        near = valid_t & ((dirs_t * dirs_t[i][None]).sum(-1) >= cos_max) & valid_t[i][None]  # (C,N)
        k = near.sum(0)
        w = near.float()[..., None]
        mean = (cols_t * w).sum(0) / k.clamp_min(1)[:, None]
        var = (((cols_t - mean[None]) ** 2) * w).sum(0).mean(-1) / k.clamp_min(1)
        ok = valid_t[i] & (k >= 2)
        if not ok.any():
            continue
        idx = torch.nonzero(ok).flatten()
        p = pix[i][idx]
        uniq, inv = torch.unique(p, return_inverse=True)
        best = torch.full((len(uniq),), float("inf"), dtype=var.dtype).scatter_reduce(0, inv, var[idx], "amin")
        chosen[idx[var[idx] <= best[inv]]] = True
    return chosen.numpy()


def _surface(cells: np.ndarray) -> np.ndarray:
    """(N,) bool: cells (integer coordinates) with a face neighbour that is not a cell."""
    if len(cells) == 0:
        return np.zeros(0, bool)
    span = cells.max(0) + 3
    key = lambda c: ((c[:, 0] + 1) * span[1] + (c[:, 1] + 1)) * span[2] + (c[:, 2] + 1)  # noqa: E731
    keys = np.sort(key(cells))
    border = np.zeros(len(cells), bool)
    for axis in range(3):
        for step in (-1, 1):
            nb = cells.copy()
            nb[:, axis] += step
            k = key(nb)
            pos = np.clip(np.searchsorted(keys, k), 0, len(keys) - 1)
            border |= keys[pos] != k
    return border


def point_colors(points: np.ndarray, cams: Sequence[Camera], masks: Sequence[np.ndarray],
                 images: Sequence[np.ndarray]) -> np.ndarray:
    """(P,3) in [0,1]: median colour of each point's pixels over the cameras whose masks hold it
    (grey where none does). ``images`` are channel-first (C,H,W) at the masks' resolution."""
    samples = np.full((len(cams), len(points), 3), np.nan, np.float32)
    for i, (cam, mask, img) in enumerate(zip(cams, masks, images)):
        ok, u, v = _masked_pixels(points, cam, mask)
        samples[i, ok] = img[:, v[ok], u[ok]].T
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns: points no mask holds
        col = np.nanmedian(samples, axis=0) if len(cams) else np.zeros((len(points), 3), np.float32)
    return np.nan_to_num(col, nan=0.5).astype(np.float32)


# --- the whole job ------------------------------------------------------------------------------

def motion_points(frame_of: Callable[[int, int], np.ndarray], cams: Sequence[Camera], num_frames: int, keyframes: Sequence[int],
                  box: np.ndarray, cfg: MotionPointsConfig, progress: bool = True,
                  mask_of: Callable[[int, int], np.ndarray] | None = None) -> MotionPoints:
    """Hull points of the moving content at ``keyframes``; ``frame_of(cam_index, frame)`` reads an
    (H,W,3) uint8 frame of ``cams[cam_index]`` (the training cameras). ``mask_of(cam_index,
    frame)``, when the capture has foreground masks (H,W bool), gives the masks instead of the
    frames' difference from their background (:func:`foreground_mask`); it returns None for a
    camera without masks, whose motion masks then are that difference."""
    from tqdm import tqdm

    cfg.validate()
    empty = MotionPoints([], np.zeros((0, 3)), np.zeros((0, 3), np.float32), np.zeros(0, np.int64),
                         {"keyframes": 0, "points": [], "moving_fraction": 0.0})
    if num_frames < 2 or len(cams) < cfg.min_views or not len(keyframes):
        return empty
    sample = evenly_spaced(num_frames, cfg.background_frames)
    with tqdm(total=len(cams) * ((len(sample) if mask_of is None else 0) + len(keyframes)), desc="motion points",
              unit="img", disable=not progress) as bar:
        small = lambda ci, f: box_downsample(frame_of(ci, f), cfg.long_side)  # noqa: E731
        bgs: dict[int, np.ndarray] = {}

        def motion_mask_of(ci: int, f: int, img: np.ndarray) -> np.ndarray:
            m = None if mask_of is None else mask_of(ci, f)
            if m is not None:
                return foreground_mask(m, cfg.long_side)
            if ci not in bgs:  # read a camera's background frames once, when it first needs them
                if mask_of is not None:
                    bar.total += len(sample)
                bgs[ci] = background([small(ci, s) for s in sample])
                bar.update(len(sample))
            return motion_mask(img, bgs[ci], cfg)

        P, C, K, counts, fractions = [], [], [], [], []
        rng = np.random.default_rng(0)
        for j, f in enumerate(keyframes):
            imgs, masks = [], []
            for ci in range(len(cams)):
                img = small(ci, f)
                imgs.append(img)
                masks.append(motion_mask_of(ci, f, img))
                bar.update(1)
            fractions.append(float(np.mean([m.mean() for m in masks])))
            hull, on_surface, _ = visual_hull(cams, masks, box, cfg)
            pts = hull[on_surface]
            if cfg.select == "photo":
                chosen = hull[photo_consistent(hull, cams, masks, imgs)]
                # no agreement anywhere (no two nearby views): the hull's surface is the better guess
                pts = chosen if len(chosen) >= cfg.min_points else pts
            if len(pts) < cfg.min_points:
                pts = np.zeros((0, 3))
            if cfg.max_points > 0 and len(pts) > cfg.max_points:
                pts = pts[np.sort(rng.choice(len(pts), cfg.max_points, replace=False))]
            P.append(pts)
            C.append(point_colors(pts, cams, masks, imgs))
            K.append(np.full(len(pts), j, np.int64))
            counts.append(int(len(pts)))
    stats = {"keyframes": len(keyframes) if sum(counts) else 0, "points": counts,
             "moving_fraction": round(float(np.mean(fractions)), 4)}
    if sum(counts) == 0:
        return MotionPoints([], empty.points, empty.colors, empty.point_keyframes, stats)
    return MotionPoints(list(keyframes), np.concatenate(P), np.concatenate(C), np.concatenate(K), stats)
