"""Time-conditioned anchors from keyframe point clouds: voxel downsampling per keyframe and
the initial log scale v (6 numbers: v[:3] scales offsets, v[3:] the base Gaussian scale).

Anchors carry the keyframe they were made from; keyframe ``STATIC`` (-1) marks anchors that are
active at every time. :func:`split_static` finds the points of content that does not move
(re-observed at most keyframes), so that it is modelled once instead of once per keyframe."""

from __future__ import annotations

from dataclasses import dataclass

import math

import numpy as np
import torch


STATIC = -1  # keyframe index of always-active anchors


@dataclass
class AnchorInit:
    mu: torch.Tensor  # (A, 3) float32
    log_scale: torch.Tensor  # (A, 6)
    keyframe: torch.Tensor  # (A,) int64
    voxel_size: float


def _random_device(generator: torch.Generator | None, like: torch.Tensor) -> torch.device:
    """Where random numbers from ``generator`` are drawn (a generator draws on its own device)."""
    return generator.device if generator is not None else like.device


def auto_voxel_size(points: torch.Tensor, sample: int = 4096, generator: torch.Generator | None = None) -> float:
    """Median nearest-neighbour spacing of (a sample of) the points."""
    points = torch.unique(points, dim=0)  # duplicated points would give a zero spacing
    if points.shape[0] < 2:
        return 0.01
    n = points.shape[0]
    sel = torch.randperm(n, generator=generator, device=_random_device(generator, points))[: min(sample, n)]
    d = knn_mean_sq_dist(points[sel], points, k=1, exclude_self=False, skip_zero=True)
    return float(d.sqrt().median().clamp_min(1e-6))


def knn_mean_sq_dist(query: torch.Tensor, ref: torch.Tensor, k: int, exclude_self: bool = True,
                     skip_zero: bool = False, chunk: int = 2048) -> torch.Tensor:
    """Mean squared distance from each query point to its k nearest reference points."""
    out = []
    chunk = max(1, min(chunk, (1 << 23) // max(1, ref.shape[0])))  # at most 64 MB of distances at once
    extra = 1 if (exclude_self or skip_zero) else 0
    kk = min(k + extra, ref.shape[0])
    for i in range(0, query.shape[0], chunk):
        d2 = torch.cdist(query[i: i + chunk].double(), ref.double()).pow(2)
        vals = d2.topk(kk, dim=1, largest=False).values
        if skip_zero:
            vals = torch.where(vals <= 1e-18, torch.full_like(vals, float("inf")), vals)
            vals = vals.sort(dim=1).values
        elif exclude_self and kk > 1:
            vals = vals[:, 1:]  # the query itself is its own nearest point (distance 0)
        vals = vals[:, :k]
        finite = torch.isfinite(vals)
        mean = torch.where(finite, vals, torch.zeros_like(vals)).sum(1) / finite.sum(1).clamp_min(1)
        out.append(mean.float())
    return torch.cat(out) if out else torch.zeros(0, device=query.device)


def voxel_downsample(points: torch.Tensor, voxel: float) -> torch.Tensor:
    """One point per occupied voxel: the voxel center (as Scaffold-GS)."""
    if points.shape[0] == 0:
        return points
    cells = torch.unique(torch.round(points / voxel).long(), dim=0)
    return cells.float() * voxel


def anchor_voxel_size(points: torch.Tensor, keyframes: torch.Tensor, voxel_size: float = 0.0,
                      generator: torch.Generator | None = None) -> float:
    """``voxel_size`` if given, else the median point spacing within keyframe groups (groups
    re-observe the same static points, so spacing across groups would be too small)."""
    if voxel_size > 0:
        return float(voxel_size)
    groups = [points[keyframes == k] for k in torch.unique(keyframes).tolist()]
    return float(np.median([auto_voxel_size(g, generator=generator) for g in groups]))


def init_anchors(points: torch.Tensor, keyframes: torch.Tensor, voxel_size: float = 0.0,
                 max_per_keyframe: int = 0, generator: torch.Generator | None = None,
                 static_voxel_factor: float = 1.0) -> AnchorInit:
    """Anchors per keyframe group: voxel downsampled points; v = log(sqrt(mean squared distance
    to the 3 nearest anchors of the same keyframe, the anchor itself included)) for all six numbers."""
    points = points.float()
    if points.shape[0] == 0:
        raise ValueError("the scene has no points to initialize anchors from (points.ply is empty)")
    voxel = anchor_voxel_size(points, keyframes, voxel_size, generator)
    mus, kfs, scales = [], [], []
    for k in torch.unique(keyframes).tolist():
        # static points pool the observations of every keyframe: they support a finer voxel
        p = voxel_downsample(points[keyframes == k], voxel * (static_voxel_factor if k == STATIC else 1.0))
        if max_per_keyframe and p.shape[0] > max_per_keyframe:
            keep = torch.randperm(p.shape[0], generator=generator, device=_random_device(generator, p))
            p = p[keep[:max_per_keyframe]]
        if p.shape[0] >= 2:
            # Mean over the 3 nearest points *including the anchor itself*, i.e. (d1^2 + d2^2) / 3:
            # smaller than SPEC's "3 nearest other anchors", chosen by measurement (cpu-fast on the
            # large-motion scene: +1.8 dB at 300 steps, +2.3 dB at 1000 steps).
            d2 = knn_mean_sq_dist(p, p, k=3, exclude_self=False)
        else:
            d2 = torch.full((p.shape[0],), voxel**2, device=p.device)
        s = d2.clamp_min(1e-7 * voxel * voxel + 1e-12).sqrt().log()
        mus.append(p)
        kfs.append(torch.full((p.shape[0],), int(k), dtype=torch.int64, device=p.device))
        scales.append(s[:, None].expand(-1, 6))
    return AnchorInit(torch.cat(mus), torch.cat(scales).contiguous(), torch.cat(kfs), float(voxel))


def split_static(points: torch.Tensor, keyframes: torch.Tensor, cell: float, min_fraction: float = 0.5
                 ) -> torch.Tensor:
    """Mask of points in static content: points whose cell (edge ``cell``, a coarse voxel that
    absorbs triangulation noise) is occupied at >= max(2, ceil(min_fraction * K)) of the K
    keyframes. Moving content occupies a cell only around the times it passes through it."""
    kf_ids = torch.unique(keyframes)
    K = kf_ids.numel()
    if K < 2 or points.shape[0] == 0:
        return torch.zeros(points.shape[0], dtype=torch.bool, device=points.device)
    cells = torch.round(points.double() / cell).long()
    uniq_cells, cell_of = torch.unique(cells, dim=0, return_inverse=True)
    # distinct (cell, keyframe) pairs -> number of keyframes that see each cell
    pair = cell_of * (int(keyframes.max()) + 2) + (keyframes + 1)
    seen_pairs = torch.unique(pair)
    count = torch.bincount(seen_pairs // (int(keyframes.max()) + 2), minlength=uniq_cells.shape[0])
    need = max(2, math.ceil(min_fraction * K))
    return count[cell_of] >= need
