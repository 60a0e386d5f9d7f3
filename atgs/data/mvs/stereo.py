"""Multi-view stereo for one keyframe: depth maps of every camera, fused into coloured points."""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from atgs.cameras import Camera
from atgs.data.mvs.config import StereoConfig
from atgs.data.mvs.fusion import capped_voxel_average, fuse_depth_maps
from atgs.data.mvs.patchmatch import DepthMap, patchmatch, refine_geometric
from atgs.data.mvs.views import View, depth_ranges, make_view, select_sources, view_scores
from atgs.threads import torch_threads

MIN_OVERLAP = 0.05  # a camera may confirm a reference depth if it sees this much of the reference view


@dataclass
class StereoResult:
    points: np.ndarray  # (N,3) float64, world
    colors: np.ndarray  # (N,3) float32 in [0,1]
    voxel: float  # the voxel the points were averaged in (world units)
    views: list[View] = field(default_factory=list)  # working-resolution cameras and images
    depth_maps: list[DepthMap | None] = field(default_factory=list)  # None: the camera had no source
    ranges: list[tuple[float, float]] = field(default_factory=list)  # (near, far) per camera
    sources: list[list[int]] = field(default_factory=list)
    seconds: dict = field(default_factory=dict)


def stereo_points(images: Sequence[np.ndarray], cameras: Sequence[Camera], cfg: StereoConfig = StereoConfig(),
                  seed_points: np.ndarray | None = None,
                  depth_hints: Sequence[tuple[float, float]] | None = None,
                  on_camera: Callable[[], None] | None = None) -> StereoResult:
    """Dense coloured points of one keyframe.

    ``images[i]`` (H,W,3 uint8) was taken by ``cameras[i]`` (undistorted, posed). ``seed_points``
    (e.g. SIFT triangulation) set each camera's depth range and guide the choice of sources;
    without them ``depth_hints`` (per-camera near/far of the dataset) or the camera layout do.
    ``on_camera`` is called after each depth map of each pass (progress bars; see
    :func:`stereo_steps`).
    """
    with torch_threads(stereo_thread_count(cfg.threads)):
        return _stereo_points(images, cameras, cfg, seed_points, depth_hints, on_camera)


def _stereo_points(images, cameras, cfg, seed_points, depth_hints, on_camera) -> StereoResult:
    t0 = time.perf_counter()
    views = [make_view(img, cam, cfg.long_side) for img, cam in zip(images, cameras)]
    wcams = [v.cam for v in views]
    ranges = depth_ranges(wcams, seed_points, hints=depth_hints)
    scores, overlap = view_scores(wcams, ranges, seed_points)
    sources = select_sources(scores, cfg.neighbors)
    t1 = time.perf_counter()
    maps: list[DepthMap | None] = []
    for r, view in enumerate(views):
        maps.append(patchmatch(view, [views[j] for j in sources[r]], *ranges[r], cfg, seed=r) if sources[r] else None)
        if on_camera is not None:
            on_camera()
    if cfg.geo_iterations > 0:  # second pass: agree with the other cameras' first-pass depths
        first = maps
        maps = []
        for r, view in enumerate(views):
            srcs = [j for j in sources[r] if first[j] is not None]
            maps.append(None if first[r] is None else refine_geometric(
                view, [views[j] for j in srcs], [first[j].depth for j in srcs], first[r], *ranges[r], cfg, seed=r))
            if on_camera is not None:
                on_camera()
    t2 = time.perf_counter()
    checks = [[j for j in range(len(views)) if j != r and max(overlap[r, j], overlap[j, r]) > MIN_OVERLAP]
              for r in range(len(views))]
    pts, cols = fuse_depth_maps(views, maps, checks, cfg)
    voxel = cfg.voxel_px * _pixel_footprint(views, maps, ranges)
    pts, cols, voxel = capped_voxel_average(pts, cols, voxel, cfg.max_points)
    t3 = time.perf_counter()
    return StereoResult(pts, cols, voxel, views, maps, ranges, sources,
                        {"setup": t1 - t0, "depth": t2 - t1, "fusion": t3 - t2})


def stereo_steps(num_cameras: int, cfg: StereoConfig) -> int:
    """How many times :func:`stereo_points` calls ``on_camera``."""
    return num_cameras * (2 if cfg.geo_iterations > 0 else 1)


def idle_cores() -> int:
    """Cores not busy according to the 1-minute load average (at least 1)."""
    n = os.cpu_count() or 1
    try:
        load = os.getloadavg()[0]
    except OSError:  # pragma: no cover - not available on this platform
        return n
    return max(1, int(n - load + 0.5))


def stereo_thread_count(threads: int) -> int:
    """Torch threads for the stereo: ``threads`` (0: :func:`idle_cores`), never more than torch
    uses now and at least 1."""
    return max(1, min(torch.get_num_threads(), threads if threads > 0 else idle_cores()))


def _pixel_footprint(views: Sequence[View], maps: Sequence[DepthMap | None],
                     ranges: Sequence[tuple[float, float]]) -> float:
    """Median over cameras of (median depth / focal length): the world size of one working pixel."""
    sizes = []
    for v, m, (near, far) in zip(views, maps, ranges):
        d = m.depth[m.depth > 0] if m is not None else None
        z = float(d.median()) if d is not None and d.numel() else float(np.sqrt(near * far))
        sizes.append(z / np.sqrt(v.cam.fx * v.cam.fy))
    return float(np.median(sizes))
