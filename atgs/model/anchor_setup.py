"""A new model's anchors from a scene's point clouds, one keyframe at a time
(``ATGSModel.from_clouds``).

The steps, each over groups (a group: one model keyframe's points, those of the scene keyframe
nearest its frame, :func:`keyframe_sources`):

1. the voxel size: the median over the groups of their point spacing (unless given);
2. the split layout's static vote: a point is static when its coarse cell (2 voxels) is occupied
   at ``static_fraction`` of the groups or more (atgs.model.anchors.split_static, counted from
   each group's cells);
3. random anchors (``random_anchors``): uniform in the bounds (or the points' box), carved by the
   space the points prove empty;
4. each model keyframe's anchors from its non-static points and its motion points, and the
   static anchors from the union of every group's static cells and the random points
   (atgs.model.anchors.init_anchors' downsampling and scales).

A step reads a group's points when it needs them and keeps only what it derives (a spacing, the
occupied cells, anchors), so the set-up holds one keyframe's points at a time, not the capture's
(docs/training.md, "Memory per worker"). With ``spread`` (several workers), worker r does the
groups i with i % world == r and every worker gathers the results; each group draws from its
own generator, so the anchors are the same however the groups are spread.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, TypeVar

import numpy as np
import torch

from atgs.geometry.free_space import FreeSpace, depth_grids, merged_grids
from atgs.geometry.seen_space import fallback_points
from atgs.keyframe_cloud import ArrayPointCloud, PointCloud
from atgs.model.anchors import STATIC, AnchorInit, auto_voxel_size, knn_mean_sq_dist
from atgs.model.random_anchors import random_anchor_points
from atgs.timeline import Timeline

if TYPE_CHECKING:
    from atgs.cameras import Camera
    from atgs.model.config import ModelConfig

T = TypeVar("T")
RANDOM = -2  # the random anchors' generator key (model keyframes are >= 0, static ones STATIC)


class Spread(Protocol):
    """Workers sharing the set-up (atgs.train.distributed.Workers)."""

    rank: int
    world: int

    def gather_everywhere(self, obj) -> list: ...


@dataclass(frozen=True)
class Group:
    """Model keyframe ``keyframe``'s points: keyframe ``source`` of ``cloud``."""

    keyframe: int
    cloud: PointCloud
    source: int

    def read(self) -> torch.Tensor:
        return torch.as_tensor(self.cloud.read(self.source), device="cpu")


def keyframe_sources(scene_keyframes: Sequence[int], timeline: Timeline, share: bool = False) -> list[tuple[int, int]]:
    """Map the scene's keyframes onto the model's K keyframes: (model keyframe j, scene keyframe
    s) pairs, j taking the points of the scene keyframe nearest its frame. Without ``share`` a
    scene keyframe goes to one model keyframe only, the one nearest its frame (the rest start
    empty); with ``share`` every model keyframe takes a copy of its nearest scene keyframe's
    points, so a model with more keyframes than the scene was prepared with has anchors at each
    (the split layout then merges the copies of static content into one static anchor)."""
    if not scene_keyframes:
        return []
    sk = np.asarray(scene_keyframes, np.int64)
    frames = timeline.keyframe_frames()
    mk = np.asarray(frames, np.int64)
    out, taken = [], set()
    for j, f in enumerate(frames):
        s = int(np.abs(sk - f).argmin())
        # without sharing, a scene keyframe goes to the model keyframe nearest to it: with more
        # model keyframes, the first one that picks it may be frames earlier than its own
        if not share and (s in taken or int(np.abs(mk - scene_keyframes[s]).argmin()) != j):
            continue
        taken.add(s)
        out.append((j, s))
    return out


def generator(seed: int, key: int) -> torch.Generator:
    """The generator of group ``key`` (a model keyframe, STATIC or RANDOM)."""
    return torch.Generator().manual_seed((seed * 1_000_003 + key + 3) % (2**63 - 1))


def each(n: int, fn: Callable[[int], T], spread: Spread | None) -> list[T]:
    """[fn(0), ..., fn(n - 1)]; with ``spread``, every worker computes its share and all gather."""
    if spread is None or spread.world == 1:
        return [fn(i) for i in range(n)]
    found: dict[int, T] = {}
    for part in spread.gather_everywhere({i: fn(i) for i in range(spread.rank, n, spread.world)}):
        found.update(part)
    return [found[i] for i in range(n)]


def fold(n: int, fn: Callable[[int], T], combine: Callable[[T, T], T], spread: Spread | None) -> T | None:
    """``combine`` (commutative and exact: a minimum, a union) over fn(0) .. fn(n - 1), each
    worker folding its share first; None when n is 0."""
    mine = range(n) if spread is None or spread.world == 1 else range(spread.rank, n, spread.world)
    local = None
    for i in mine:
        v = fn(i)
        local = v if local is None else combine(local, v)
    parts = [local] if spread is None or spread.world == 1 else spread.gather_everywhere(local)
    out = None
    for v in parts:
        if v is not None:
            out = v if out is None else combine(out, v)
    return out


def cells_of(points: torch.Tensor, size: float) -> torch.Tensor:
    """(n, 3) int64: the cells of edge ``size`` the points lie in (as voxel_downsample rounds)."""
    return torch.round(points / size).long()


def occupied(points: torch.Tensor, size: float) -> torch.Tensor:
    """(U, 3) int64, sorted: the distinct cells of ``points``."""
    return torch.unique(cells_of(points, size), dim=0)


def member(rows: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
    """(n,) bool: which of ``rows`` (n, 3) appear in ``table`` (U, 3)."""
    if len(rows) == 0 or len(table) == 0:
        return torch.zeros(len(rows), dtype=torch.bool, device="cpu")
    u, inv = torch.unique(torch.cat([table, rows]), dim=0, return_inverse=True)
    hit = torch.zeros(len(u), dtype=torch.bool, device="cpu")
    hit[inv[:len(table)]] = True
    return hit[inv[len(table):]]


def _union(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.unique(torch.cat([a, b]), dim=0)


def group_anchors(cells: torch.Tensor, size: float, voxel: float, max_count: int, gen: torch.Generator
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """One group's anchors from its occupied cells (sorted, of edge ``size``): the cell
    centres, at most ``max_count`` of them (0: all), and v = log(sqrt(mean squared distance to
    the 3 nearest anchors of the group, itself included)) for all six numbers, at least about
    1e-3.5 ``voxel`` (the base voxel size; init_anchors)."""
    p = cells.float() * size
    if max_count and p.shape[0] > max_count:
        p = p[torch.randperm(p.shape[0], generator=gen, device="cpu")[:max_count]]
    if p.shape[0] >= 2:
        d2 = knn_mean_sq_dist(p, p, k=3, exclude_self=False)
    else:
        d2 = torch.full((p.shape[0],), voxel**2, device="cpu")
    s = d2.clamp_min(1e-7 * voxel * voxel + 1e-12).sqrt().log()
    return p, s[:, None].expand(-1, 6).contiguous()


def anchors_from_clouds(cfg: "ModelConfig", timeline: Timeline, cloud: PointCloud, scene_keyframes: Sequence[int],
                        motion_cloud: PointCloud | None, motion_keyframes: Sequence[int],
                        cameras: "Sequence[Camera]", bounds: torch.Tensor | None, seed: int,
                        spread: Spread | None = None) -> AnchorInit:
    """The anchors of a new model (module docstring). ``cameras``: the training cameras (they
    carve the random anchors, and fill an empty scene); ``bounds``: the scene's box (random
    anchors; None: the points')."""
    split = cfg.anchor_layout == "split"
    geometry, motion, fallback = _groups(timeline, split, cloud, scene_keyframes, motion_cloud, motion_keyframes,
                                         cameras, seed)
    voxel = cfg.voxel_size if cfg.voxel_size > 0 else float(np.median(each(
        len(geometry), lambda i: auto_voxel_size(geometry[i].read(), generator=generator(seed, geometry[i].keyframe)),
        spread)))
    static_cells = _static_vote(geometry, 2 * voxel, cfg.static_fraction, spread) if split and not fallback else None
    extra = _random_points(cfg, geometry + motion, cameras if cfg.carve_random_anchors and not fallback else [],
                           bounds, seed, spread) if cfg.random_anchors > 0 else torch.zeros(0, 3, device="cpu")

    static_voxel = voxel * cfg.static_voxel_factor
    by_keyframe = {g.keyframe: g for g in geometry}
    motion_of = {g.keyframe: g for g in motion}
    keyframes = sorted({g.keyframe for g in geometry + motion if g.keyframe != STATIC} |
                       ({0} if len(extra) and not split else set()))

    def keyframe_part(i: int) -> tuple[tuple[torch.Tensor, torch.Tensor], torch.Tensor | None]:
        """Keyframe ``keyframes[i]``'s anchors (positions, log scales), and its static points'
        cells (of the static voxel)."""
        j = keyframes[i]
        moving, static = [], None
        if j in by_keyframe:
            p = by_keyframe[j].read()
            if static_cells is not None:
                still = member(cells_of(p.double(), 2 * voxel), static_cells)
                static, p = occupied(p[still], static_voxel), p[~still]
            moving.append(p)
        if j in motion_of:
            moving.append(motion_of[j].read())
        if j == 0 and not split:
            moving.append(extra)
        cells = occupied(torch.cat(moving), voxel)
        return group_anchors(cells, voxel, voxel, cfg.max_anchors_per_keyframe, generator(seed, j)), static

    parts = each(len(keyframes), keyframe_part, spread)
    statics = [s for _, s in parts if s is not None]
    if STATIC in by_keyframe:  # the empty scene's fill, static in the split layout
        statics.append(occupied(by_keyframe[STATIC].read(), static_voxel))
    if split and len(extra):
        statics.append(occupied(extra, static_voxel))
    groups = []  # (keyframe, (positions, log scales)): the static anchors first (every worker builds them)
    if statics:
        groups.append((STATIC, group_anchors(torch.unique(torch.cat(statics), dim=0), static_voxel, voxel,
                                             cfg.max_anchors_per_keyframe, generator(seed, STATIC))))
    groups += [(j, anchors) for j, (anchors, _) in zip(keyframes, parts)]
    mus = [mu for _, (mu, _) in groups if len(mu)]
    scales = [s for _, (mu, s) in groups if len(mu)]
    kfs = [torch.full((len(mu),), j, dtype=torch.int64, device="cpu") for j, (mu, _) in groups if len(mu)]
    if not mus:
        raise ValueError("the scene has no points to initialize anchors from (points.ply is empty)")
    return AnchorInit(torch.cat(mus), torch.cat(scales), torch.cat(kfs), float(voxel))


def _groups(timeline: Timeline, split: bool, cloud: PointCloud, scene_keyframes: Sequence[int],
            motion_cloud: PointCloud | None, motion_keyframes: Sequence[int], cameras: "Sequence[Camera]",
            seed: int) -> tuple[list[Group], list[Group], bool]:
    """(the geometry groups, the motion groups, whether the geometry is the empty scene's fill)."""
    K = timeline.num_keyframes
    has_motion = motion_cloud is not None and len(motion_keyframes) > 0
    # more model keyframes than prepared ones: each takes its nearest prepared keyframe's points
    # (split only: there the copies of static content merge; per-keyframe would multiply it)
    # (not with motion points: those place moving content at the other keyframes, where a copy
    # of the nearest keyframe's moving points would be in the wrong place)
    share = split and K > len(scene_keyframes) and not has_motion
    geometry = [Group(j, cloud, s) for j, s in keyframe_sources(scene_keyframes, timeline, share) if cloud.count(s)]
    fallback = not geometry
    if fallback:  # an empty points.ply: start from the space the cameras see
        pts = fallback_points(list(cameras), seed=seed)
        print(f"warning: the scene has no points (points.ply is empty); starting from {len(pts)} points filling "
              "the space the cameras see", file=sys.stderr)
        filled = ArrayPointCloud(pts, np.zeros(len(pts)), 1)
        geometry = [Group(STATIC, filled, 0)] if split else [Group(j, filled, 0) for j in range(K)]
    motion = []
    if has_motion:  # moving by construction: never static, never part of the split's vote
        mshare = split and K > len(motion_keyframes)
        motion = [Group(j, motion_cloud, s) for j, s in keyframe_sources(motion_keyframes, timeline, mshare)
                  if motion_cloud.count(s)]
    return geometry, motion, fallback


def _static_vote(geometry: list[Group], cell: float, fraction: float, spread: Spread | None) -> torch.Tensor | None:
    """The cells (edge ``cell``) occupied at max(2, ceil(fraction x groups)) groups or more; None
    with fewer than two groups (nothing can be told static)."""
    if len(geometry) < 2:
        return None
    cells = each(len(geometry), lambda i: occupied(geometry[i].read().double(), cell), spread)
    table, counts = torch.unique(torch.cat(cells), dim=0, return_counts=True)
    return table[counts >= max(2, math.ceil(fraction * len(geometry)))]


def _random_points(cfg: "ModelConfig", groups: list[Group], cameras: "Sequence[Camera]", bounds: torch.Tensor | None,
                   seed: int, spread: Spread | None) -> torch.Tensor:
    """``cfg.random_anchors`` points in the bounds (or the points' box), outside the space the
    points prove empty for ``cameras`` (none: not carved)."""
    if bounds is not None:
        box = bounds.float().cpu()
    else:
        box = fold(len(groups), lambda i: _box(groups[i].read()),
                   lambda a, b: torch.stack([torch.minimum(a[0], b[0]), torch.maximum(a[1], b[1])]), spread)
    free = None
    if cameras:
        # (the free-space loss, atgs.train.scene_setup.free_space_of, folds the scene's measured
        # points instead, not the fill: each selection kept as it was, for fixed-seed runs)
        grids = fold(len(groups), lambda i: depth_grids(cameras, groups[i].read().numpy()), merged_grids, spread)
        free = FreeSpace.of_grids(cameras, grids)
    return random_anchor_points(cfg.random_anchors, box, free, generator(seed, RANDOM))


def _box(p: torch.Tensor) -> torch.Tensor:
    return torch.stack([p.min(0).values, p.max(0).values])
