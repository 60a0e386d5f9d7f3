"""An independent decode of one frame in float64, for tests of both model decodes.

Written from the method's formulas (shared/SPEC.md section 1, docs/model.md: time convention,
anchor layout, anchor motion, 3D smoothing, camera clearance) and the documented layout of the
tables (HashGrid4D, SpatialGrid); it reads the model's parameters and configuration and calls
none of its code. Dense and slow on purpose: every anchor, every grid corner, every level.
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction
import math

import torch

STATIC = -1  # an anchor of every keyframe
PRIMES = (1, 2654435761, 805459861, 3674653429)  # Instant-NGP's spatial hash
FADE_LEVEL = 1.0 / 255.0  # no anchor decoded below this fade weight
MIN_FADE_WIDTH = 1e-3  # narrowest fade width, keyframe intervals
VIEW_MARGIN = 0.15  # a camera sees an anchor inside its image grown by this, beyond the model's near plane


@dataclass
class ReferenceFrame:
    """The drawn Gaussians of a frame, in anchor order then slot order (float64)."""

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor
    anchor_ids: torch.Tensor
    slot_ids: torch.Tensor


def _round_half_up(x: Fraction) -> int:
    return math.floor(x + Fraction(1, 2))


def keyframe_frame(j: int, F: int, K: int) -> int:
    return 0 if K == 1 else _round_half_up(Fraction(j * (F - 1), K - 1))


def window(f: int, F: int, K: int, W: int) -> tuple[int, int]:
    """Keyframe window of frame f: the nearest keyframe (first one on ties) +- W // 2."""
    if W == 0 or K == 1 or F == 1:
        return 0, K - 1
    t = Fraction(f, F - 1) * (K - 1)  # the frame in keyframe intervals
    kbar = min(range(K), key=lambda j: abs(t - j))
    h = W // 2
    return max(0, kbar - h), min(K - 1, kbar + h)


def multilinear(x: torch.Tensor, res: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Corners (N, 2^d, d) and weights (N, 2^d) of points x (N, d) in [0, 1]^d on a grid of
    res[i] cells along axis i (the last cell closed)."""
    r = torch.tensor(res, dtype=torch.float64)
    pos = x.clamp(0, 1) * r
    cell = torch.minimum(pos.floor(), r - 1).clamp_min(0)
    frac = pos - cell
    d = x.shape[1]
    corners, weights = [], []
    for c in range(2 ** d):
        bits = torch.tensor([(c >> i) & 1 for i in range(d)], dtype=torch.float64)
        corners.append(cell + bits)
        weights.append(torch.where(bits.bool(), frac, 1 - frac).prod(dim=1))
    return torch.stack(corners, 1).long(), torch.stack(weights, 1)


def spatial_features(table: torch.Tensor, res: int, x: torch.Tensor) -> torch.Tensor:
    """F_s: trilinear over res^3 vertices on [0, 1]^3, vertex (i, j, k) at row i + res (j + res k)."""
    corners, w = multilinear(x, [res - 1] * 3)
    rows = corners[..., 0] + res * (corners[..., 1] + res * corners[..., 2])
    return (table.double()[rows] * w[..., None]).sum(1)


def hash_features(model, x: torch.Tensor, tau: float, m: int) -> torch.Tensor:
    """F_T,m: per level, quadrilinear over the 4D vertices (x, y, z, time) of that level's table
    block, indexed densely where they fit, else hashed; levels concatenated."""
    h = model.cfg.hash
    T = 2 ** h.log2_table_size
    table = model.hash.table.double()
    x4 = torch.cat([x, torch.full((x.shape[0], 1), float(tau), dtype=torch.float64)], 1)
    out = []
    for lv in range(h.levels):
        r = max(1, math.floor(h.base_resolution * h.growth ** lv))
        rt = max(1, min(r, h.max_time_resolution))
        corners, w = multilinear(x4, [r, r, r, rt])
        cx, cy, cz, ct = (corners[..., i].tolist() for i in range(4))
        dense = (r + 1) ** 3 * (rt + 1) <= T
        slots = []
        for row in zip(cx, cy, cz, ct):
            slots.append([a + (r + 1) * (b + (r + 1) * (c + (r + 1) * t)) if dense
                          else (a * PRIMES[0] ^ b * PRIMES[1] ^ c * PRIMES[2] ^ t * PRIMES[3]) & (T - 1)
                          for a, b, c, t in zip(*row)])
        rows = torch.tensor(slots) + (m * h.levels + lv) * T
        out.append((table[rows] * w[..., None]).sum(1))
    return torch.cat(out, 1)


def mlp(x: torch.Tensor, state: dict, name: str) -> torch.Tensor:
    """A two-layer head: Linear, ReLU, Linear."""
    w1, b1, w2, b2 = (state[f"{name}.{i}.{p}"].double() for i, p in ((0, "weight"), (0, "bias"), (2, "weight"), (2, "bias")))
    return torch.relu(x @ w1.T + b1) @ w2.T + b2


def smoothing_variance(model, mu: torch.Tensor) -> torch.Tensor:
    """Mip-Splatting's 3D filter: size / nu^2, nu the highest focal / depth of a training camera
    seeing the anchor beyond the model's near plane (0: none sees it)."""
    held_out = set(model.test_camera_names)
    cams = [c for c in model.cameras if c.name not in held_out] or model.cameras
    best = torch.zeros(mu.shape[0], dtype=torch.float64)
    for cam in cams:
        p = mu @ torch.as_tensor(cam.R, dtype=torch.float64).T + torch.as_tensor(cam.t, dtype=torch.float64)
        z = p[:, 2]
        u = cam.fx * p[:, 0] / z + cam.cx
        v = cam.fy * p[:, 1] / z + cam.cy
        mw, mh = VIEW_MARGIN * cam.width, VIEW_MARGIN * cam.height
        seen = (z > model.near) & (u > -mw) & (u < cam.width + mw) & (v > -mh) & (v < cam.height + mh)
        best = torch.where(seen, torch.maximum(best, max(cam.fx, cam.fy) / z), best)
    return torch.where(best > 0, model.cfg.smoothing_3d / best.clamp_min(1e-300) ** 2, torch.zeros_like(best))


def max_fade_width(F: int, K: int, W: int) -> float:
    """The widest fade: at 1/256 by the first frame outside the window, less half a frame of
    keyframe rounding (docs/model.md, "Anchor motion")."""
    h = W // 2
    if W == 0 or h == 0 or K <= 1 or F <= 1:
        return math.inf
    rounding = 0.0 if (F - 1) % (K - 1) == 0 else min(0.5, 0.5 * (K - 1) / (F - 1))
    return (h + 0.5 - rounding) / math.sqrt(2 * math.log(256))


def reference_frame(model, f: int | None = None, t: float | None = None) -> ReferenceFrame:
    """The Gaussians drawn at frame f, or at normalized time t (clamped to [0, 1]): the window
    and segment of its nearest frame (halves up), the local time of t itself."""
    cfg, tl = model.cfg, model.timeline
    F, K, W, M = tl.num_frames, tl.num_keyframes, cfg.window, tl.num_segments
    if t is not None:
        t = min(1.0, max(0.0, t))
        f = math.floor(t * (F - 1) + 0.5)
    m = min(M - 1, math.floor(Fraction(M * f, F - 1)))
    tau = float(Fraction(M * f, F - 1) - m) if t is None else min(1.0, max(0.0, M * t - m))
    lo, hi = window(f, F, K, W)
    k = model.anchor_keyframe
    active = ((k >= lo) & (k <= hi)) | (k == STATIC)
    if cfg.anchor_layout == "per-keyframe" and cfg.static_keyframe0:
        active |= k == 0
    ids = active.nonzero().squeeze(1)
    kf = k[ids]
    # anchor motion: signed distance in keyframe intervals to the anchor's keyframe, 0 if static
    kf_frames = torch.tensor([keyframe_frame(j, F, K) for j in range(K)], dtype=torch.float64)
    per_frame = (K - 1) / (F - 1) if K > 1 else 0.0
    dist = torch.where(kf >= 0, (f - kf_frames[kf.clamp_min(0)]) * per_frame, torch.zeros(len(ids), dtype=torch.float64))
    fade = torch.ones(len(ids), dtype=torch.float64)
    if cfg.temporal_fade:
        width = model.anchor_fade[ids, 0].double().exp().clamp(MIN_FADE_WIDTH, max_fade_width(F, K, W))
        fade = torch.exp(-dist ** 2 / (2 * width ** 2))
        shown = fade >= max(FADE_LEVEL, cfg.opacity_threshold)
        ids, dist, fade = ids[shown], dist[shown], fade[shown]
    mu = model.anchor_mu[ids].double()
    v = model.anchor_log_scale[ids].double()
    x = (mu - model.bbox_min.double()) / (model.bbox_max.double() - model.bbox_min.double())
    inside = ((x >= 0) & (x <= 1)).all(1, keepdim=True).double()  # outside the box: no grid features
    fa = model.anchor_feature[ids].double()
    if cfg.use_spatial_grid:
        fa = fa + inside * spatial_features(model.spatial.table, model.spatial.res, x)
    h = inside * hash_features(model, x, tau, m)
    ft = torch.relu(h @ model.tmlp_w1[m].double() + model.tmlp_b1[m].double()) @ model.tmlp_w2[m].double() \
        + model.tmlp_b2[m].double()
    fw = torch.cat([fa, ft], 1)
    state = model.decoder.state_dict()
    n, q = len(ids), cfg.gaussians_per_anchor
    opac = torch.sigmoid(mlp(fw, state, "opacity")).view(n, q)
    cov = mlp(fw, state, "cov").view(n, q, 7)
    scales = v[:, None, 3:].exp() * torch.sigmoid(cov[..., :3])
    quats = cov[..., 3:] / cov[..., 3:].norm(dim=-1, keepdim=True)
    colors = torch.sigmoid(mlp(fw, state, "color")).view(n, q, 3)
    means = mu[:, None] + mlp(fw, state, "offset").view(n, q, 3) * v[:, None, :3].exp()
    if cfg.smoothing_3d > 0:
        var = smoothing_variance(model, mu)[:, None, None]
        filtered = torch.sqrt(scales ** 2 + var)
        opac = opac * (scales / filtered).prod(-1)
        scales = filtered
    opac = opac * fade[:, None]
    if cfg.anchor_velocity:
        means = means + (dist[:, None] * model.anchor_velocity[ids].double())[:, None]
    keep = torch.ones(n, q, dtype=torch.bool)
    if cfg.opacity_threshold > 0:
        keep &= opac > cfg.opacity_threshold
    radius = model.clearance.radius
    held_out = set(model.test_camera_names)
    train = [c for c in model.cameras if c.name not in held_out]
    for cam in train if radius > 0 else []:  # no Gaussian inside a training camera's housing
        keep &= (means - torch.as_tensor(cam.center, dtype=torch.float64)).norm(dim=-1) >= radius
    anchor_ids = ids[:, None].expand(n, q)
    slot_ids = torch.arange(q).expand(n, q)
    return ReferenceFrame(means[keep], quats[keep], scales[keep], opac[keep], colors[keep], anchor_ids[keep],
                          slot_ids[keep])
