"""Initial velocities of the per-keyframe anchors from the training images (scene flow).

A per-keyframe anchor moves with a learned velocity (atgs.model.anchor_motion), which starts at 0.
On the built-in large-motion scene the learned velocities ended at about 0.4x the true speeds after a
20-minute run (median 0.11 against 0.26 world units per keyframe interval): a velocity gets a
gradient only away from its keyframe, and two neighbouring keyframes' anchors cross-fading in
place explain the images nearly as well, so moving objects stay blurred. This module measures the
motion instead of waiting for it to be learned:

1. at each motion keyframe f, up to ``max_tracked`` of the keyframe's anchors are projected into
   every training camera and tracked to frames f - 1 and f + 1 with pyramidal Lucas-Kanade
   (atgs.data.flow); the central difference is the point's image velocity in that camera, kept
   where the tracking residual is low and the image window has texture;
2. each camera's image velocity u_j constrains the 3D velocity v through the projection's
   Jacobian, J_j v = u_j (two equations); the cameras that see something else at that pixel (an
   occluder, the background) disagree, so v is fitted robustly: every pair of cameras proposes a
   v, the one most cameras agree with (within ``inlier_px``) wins and is refitted on them; a point
   needs ``min_cameras`` agreeing cameras;
3. the other anchors of the keyframe take the median velocity of their nearest tracked anchors
   (within ``radius`` voxels); anchors with none keep 0.

Velocities are in world units per keyframe interval, the model's unit. Anchors of the static
layout (keyframe STATIC) are not touched.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from atgs.cameras import Camera, pinhole_jacobian, pinhole_pixels, to_camera_frame
from atgs.data.flow import pyramid, track_points


@dataclass(frozen=True)
class SceneFlowConfig:
    max_tracked: int = 256  # anchors tracked per keyframe; the others take their neighbours' velocity
    long_side: int = 480  # working resolution (long side, pixels); larger images are area-downscaled
    window: int = 9  # Lucas-Kanade window (pixels)
    levels: int = 4  # pyramid levels
    max_residual: float = 0.08  # RMS window difference (grey, 0..1) above which a track is dropped
    inlier_px: float = 0.75  # image-velocity disagreement (pixels per frame) of an agreeing camera
    min_cameras: int = 3  # agreeing cameras a tracked anchor needs
    # A Gaussian prior on the velocity (zero mean, this many voxels per frame) against tracking
    # noise of ``noise_px``: directions the cameras hardly see (depth, for a front-facing rig of
    # close cameras) stay near 0 instead of taking the noise amplified.
    prior_voxels_per_frame: float = 1.0
    noise_px: float = 0.5
    neighbours: int = 4  # tracked anchors whose median velocity an untracked one takes
    radius: float = 3.0  # ... within this many voxels


def _project(cam: Camera, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pixels (N, 2), depths (N,) and the projection's Jacobians (N, 2, 3) of world points x."""
    pc = to_camera_frame(cam, x)
    z = pc[:, 2].clamp_min(1e-6)
    return torch.stack(pinhole_pixels(cam, pc, z), 1), pc[:, 2], pinhole_jacobian(cam, pc, z)


def robust_velocity(jac: torch.Tensor, flow: torch.Tensor, valid: torch.Tensor, inlier_px: float,
                    min_cameras: int, ridge: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """3D velocities (N, 3) from per-camera image velocities: ``jac`` (N, C, 2, 3), ``flow``
    (N, C, 2), ``valid`` (N, C). Every pair of valid cameras proposes the least-squares velocity of
    its four equations; the proposal with the most cameras within ``inlier_px`` wins and is
    refitted on them. ``ridge`` (squared pixels per squared velocity unit) is added to the normal
    equations: a zero-mean prior. Returns (velocities, ok (N,)), ok where at least
    ``min_cameras`` agree."""
    n, c = valid.shape
    if n == 0 or c < 2:
        return torch.zeros(n, 3, device=jac.device), torch.zeros(n, dtype=torch.bool, device=jac.device)
    ia, ib = torch.triu_indices(c, c, 1)
    A = torch.cat([jac[:, ia], jac[:, ib]], 2)  # (N, P, 4, 3)
    b = torch.cat([flow[:, ia], flow[:, ib]], 2)  # (N, P, 4)
    pair_ok = valid[:, ia] & valid[:, ib]
    v = _lstsq(A, b, ridge)  # (N, P, 3)
    pred = torch.einsum("ncij,npj->npci", jac, v)  # (N, P, C, 2)
    err = (pred - flow[:, None]).norm(dim=-1)
    agree = (err < inlier_px) & valid[:, None, :]
    votes = torch.where(pair_ok, agree.sum(-1), torch.full_like(pair_ok, -1, dtype=torch.long))
    best = votes.argmax(1)
    inl = agree[torch.arange(n, device=best.device), best]  # (N, C)
    w = inl.float()[..., None]
    A2 = (jac * w[..., None]).reshape(n, 2 * c, 3)
    b2 = (flow * w).reshape(n, 2 * c)
    v = _lstsq(A2, b2, ridge)
    ok = inl.sum(1) >= max(2, min_cameras)
    return torch.where(ok[:, None], v, torch.zeros_like(v)), ok


def _lstsq(A: torch.Tensor, b: torch.Tensor, ridge: float = 0.0) -> torch.Tensor:
    """Batched least squares of A (..., m, 3) v = b (..., m) through the 3x3 normal equations,
    plus ``ridge`` on the diagonal (and a tiny relative damping: a degenerate system gives a small
    v, not a huge one)."""
    AtA = A.transpose(-1, -2) @ A
    Atb = (A.transpose(-1, -2) @ b[..., None])[..., 0]
    damp = ridge + 1e-6 * AtA.diagonal(dim1=-2, dim2=-1).sum(-1).clamp_min(1e-12)
    AtA = AtA + damp[..., None, None] * torch.eye(3, device=A.device)
    return torch.linalg.solve(AtA, Atb)


def initial_velocities(anchor_mu: torch.Tensor, anchor_keyframe: torch.Tensor, voxel: float,
                       keyframe_frames: Sequence[int], num_frames: int, cameras: Sequence[Camera],
                       grey: Callable[[int, int], torch.Tensor], cfg: SceneFlowConfig = SceneFlowConfig(),
                       progress: Callable[[int, int], None] | None = None,
                       keyframes: Sequence[int] | None = None) -> tuple[torch.Tensor, dict]:
    """Velocities (A, 3) of the anchors (CPU tensors in and out), world units per keyframe interval (0 where unmeasured and
    for static anchors), and statistics. ``grey(camera_index, frame)`` is the (H, W) grey image
    (0..1) of ``cameras[camera_index]`` at ``frame``. ``keyframes``: measure only these
    keyframes' anchors (the others keep 0; each keyframe draws from its own generator, so a
    keyframe's velocities do not depend on which others are measured)."""
    A = anchor_mu.shape[0]
    vel = torch.zeros(A, 3, device="cpu")
    K = len(keyframe_frames)
    stats = {"keyframes": 0, "tracked": 0, "measured": 0, "filled": 0}
    if K < 2 or num_frames < 2 or len(cameras) < 2:
        return vel, stats
    per_interval = (num_frames - 1) / (K - 1)  # frames per keyframe interval
    ridge = (cfg.noise_px / max(cfg.prior_voxels_per_frame * voxel, 1e-9)) ** 2
    wanted = range(K) if keyframes is None else set(keyframes)
    work = [c.scaled(cfg.long_side / max(c.width, c.height)) if max(c.width, c.height) > cfg.long_side else c
            for c in cameras]
    # cameras of one working size are tracked together (one batch of image pairs)
    groups: dict[tuple[int, int], list[int]] = {}
    for ci, c in enumerate(work):
        groups.setdefault((c.height, c.width), []).append(ci)
    pyramids: dict[tuple[tuple[int, int], int], list[torch.Tensor]] = {}  # of the current keyframe's frames

    def pyr(size: tuple[int, int], f: int) -> list[torch.Tensor]:
        key = (size, f)
        if key not in pyramids:
            imgs = []
            for ci in groups[size]:
                img = grey(ci, f).float()
                if tuple(img.shape) != size:
                    img = F.interpolate(img[None, None], size=size, mode="area")[0, 0]
                imgs.append(img)
            pyramids[key] = pyramid(torch.stack(imgs), cfg.levels)
        return pyramids[key]

    margin = cfg.window / 2 + 1
    for k, f in enumerate(keyframe_frames):
        rows = (anchor_keyframe == k).nonzero().squeeze(1)
        if progress is not None:
            progress(k, K)
        pyramids.clear()
        if rows.numel() == 0 or k not in wanted:
            continue
        stats["keyframes"] += 1
        gen = torch.Generator().manual_seed(k)
        sub = rows if rows.numel() <= cfg.max_tracked else rows[torch.randperm(rows.numel(), generator=gen, device="cpu")[:cfg.max_tracked]]
        x = anchor_mu.index_select(0, sub).float()
        n = x.shape[0]
        neigh = [g for g in (f - 1, f + 1) if 0 <= g < num_frames]
        proj = [_project(cam, x) for cam in work]
        flow = torch.zeros(n, len(work), 2, device="cpu")
        valid = torch.zeros(n, len(work), dtype=torch.bool, device="cpu")
        for size, cis in groups.items():
            h, w = size
            uv = torch.stack([proj[ci][0] for ci in cis])  # (B, N, 2)
            z = torch.stack([proj[ci][1] for ci in cis])
            ok = (z > 1e-3) & (uv[..., 0] > margin) & (uv[..., 0] < w - margin) & (uv[..., 1] > margin) & \
                (uv[..., 1] < h - margin)
            start = torch.stack([uv[..., 0].clamp(0, w), uv[..., 1].clamp(0, h)], -1)  # outside ones: masked
            ends = []
            for g in neigh:
                to, res = track_points(pyr(size, f), pyr(size, g), start, cfg.window)
                ends.append(to)
                ok &= res < cfg.max_residual
            if len(ends) == 2:
                u = 0.5 * (ends[1] - ends[0])
            else:
                u = (ends[0] - start) / float(neigh[0] - f)
            ok &= torch.isfinite(u).all(-1)
            flow[:, cis] = torch.where(ok[..., None], u, torch.zeros_like(u)).transpose(0, 1)
            valid[:, cis] = ok.transpose(0, 1)
        jac = torch.stack([p[2] for p in proj], 1)
        v, ok = robust_velocity(jac, flow, valid, cfg.inlier_px, cfg.min_cameras, ridge)
        stats["tracked"] += int(sub.numel())
        stats["measured"] += int(ok.sum())
        if not bool(ok.any()):
            continue
        src, sv = anchor_mu.index_select(0, sub[ok]).float(), v[ok] * per_interval
        d = torch.cdist(anchor_mu.index_select(0, rows).float(), src)
        kk = min(cfg.neighbours, src.shape[0])
        dist, nn = d.topk(kk, dim=1, largest=False)
        cand = sv[nn]  # (R, kk, 3)
        near = dist < cfg.radius * voxel
        cand = torch.where(near[..., None], cand, torch.full_like(cand, math.nan))
        med = cand.nanmedian(dim=1).values
        has = near.any(1)
        vel[rows[has]] = med[has]
        stats["filled"] += int(has.sum())
    return vel, stats


def grey_of(image: np.ndarray) -> torch.Tensor:
    """(H, W, 3) uint8 -> (H, W) float grey in 0..1 (Rec. 601 weights)."""
    rgb = torch.tensor(np.asarray(image), dtype=torch.float32, device="cpu") / 255.0  # a copy: cached frames are read-only
    return rgb @ torch.tensor([0.299, 0.587, 0.114], device="cpu")
