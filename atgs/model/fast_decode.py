"""Fast inference decode (``gaussians_at`` / ``gaussians_at_frame``, no autograd, no camera).

Only the local time tau changes between frames, so everything that depends on the anchors alone
is computed once per parameter state and kept:

- per anchor: ``inside``, ``exp(v)``, ``f_a + f_s`` and the spatial part of every hash level's
  corner slots with its trilinear weights;
- per keyframe window (the last two): the active anchors, their rows of the above, and their
  ``f_a + f_s`` times that half of the four decoder heads' first layers (stacked into one
  matrix, biases included);
- per (segment, level, time vertex) of the 4D hash grid: the trilinear spatial interpolation of
  that time slice for every anchor (the 4D quadrilinear interpolation is the time-weighted sum
  of two such slices), built lazily and kept in a memory-bounded LRU.

A frame then costs two cached slices per level, the small per-segment MLP, one matmul for the
time half of the stacked first layers, and the four heads' second layers. The cache is keyed on
the identity and in-place version counter (``Tensor._version``) of every tensor it was built
from, so a checkpoint load, an optimizer step (in-place ``index_copy_`` / Adam) or an anchor
edit (new tensors) invalidates it. Results equal the training path (``ATGSModel._decode``) up to
float32 summation order; tests/test_model_decode_speed_equivalence.py checks this.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
import threading
from typing import TYPE_CHECKING

import torch
from torch import nn

from atgs.gaussians import Gaussians
from atgs.model.decoder import GaussianDecoder
from atgs.model.smoothing import smooth

if TYPE_CHECKING:  # pragma: no cover
    from atgs.model.atgs_model import ATGSModel

# Bytes of hash-slice cache kept per model (at least two slices per level are always kept).
SLICE_CACHE_BYTES = 256 * 2**20


def _key(tensors: list[torch.Tensor]) -> list[tuple[torch.Tensor, int]]:
    return [(t, t._version) for t in tensors]


def _same(a: list[tuple[torch.Tensor, int]], b: list[tuple[torch.Tensor, int]]) -> bool:
    return len(a) == len(b) and all(x is y and vx == vy for (x, vx), (y, vy) in zip(a, b))


def plain_heads(decoder: nn.Module) -> list[tuple[nn.Linear, nn.Linear]] | None:
    """The (first, second) Linear layers of the four heads, or None if a head is not the plain
    Linear-ReLU-Linear MLP (e.g. the reduced-precision wrapper of atgs.model.precision)."""
    if not isinstance(decoder, GaussianDecoder):
        return None
    out = []
    for name in GaussianDecoder.HEADS:
        head = getattr(decoder, name)
        if not (isinstance(head, nn.Sequential) and len(head) == 3 and isinstance(head[0], nn.Linear)
                and isinstance(head[1], nn.ReLU) and isinstance(head[2], nn.Linear)
                and head[0].weight.dtype == torch.float32 and head[2].weight.dtype == torch.float32):
            return None
        out.append((head[0], head[2]))
    return out


@dataclass
class _Features:
    key: list[tuple[torch.Tensor, int]]
    inside: torch.Tensor  # (N, 1) float
    fa: torch.Tensor  # (N, D) f_a + f_s
    scale_off: torch.Tensor  # (N, 3) exp(v[:3])
    scale_base: torch.Tensor  # (N, 3) exp(v[3:])
    partial: list[torch.Tensor]  # per level (N, 8) int64 spatial part of the hash slots
    weights: list[torch.Tensor]  # per level (N, 8) trilinear weights
    slices: "OrderedDict[tuple[int, int, int], torch.Tensor]"  # (m, level, vertex) -> (N, F)
    windows: "OrderedDict[tuple, _Window]"  # keyframe window -> its active anchors' rows


@dataclass
class _Window:
    """Rows of the anchors active in one keyframe window (frames of a window share them)."""

    active: torch.Tensor  # (A,) int64
    mu: torch.Tensor  # (A, 3)
    scale_off: torch.Tensor  # (A, 3)
    scale_base: torch.Tensor  # (A, 3)
    pre: torch.Tensor | None  # (A, H) (f_a + f_s) @ w_a + b1, filled on first use
    pre_of: object | None  # the _Heads that ``pre`` was taken from


@dataclass
class _Heads:
    key: list[tuple[torch.Tensor, int]]
    features_key: list[tuple[torch.Tensor, int]]
    b1: torch.Tensor  # (H,) first-layer biases of the four heads, stacked
    w_a: torch.Tensor  # (D, H) (f_a + f_s) half of the stacked first layers, transposed
    w_t: torch.Tensor  # (D, H) f_t half, transposed
    splits: list[int]  # hidden size of each head
    second: list[tuple[torch.Tensor, torch.Tensor]]  # (W2.T contiguous, b2) per head


class InferenceCache:
    """Per-model cache of the time-invariant decode quantities (thread safe)."""

    def __init__(self, slice_cache_bytes: int = SLICE_CACHE_BYTES) -> None:
        self.slice_cache_bytes = int(slice_cache_bytes)
        self._lock = threading.Lock()
        self._features: _Features | None = None
        self._heads: _Heads | None = None

    def clear(self) -> None:
        with self._lock:
            self._features, self._heads = None, None

    # --- cached quantities -------------------------------------------------------------------
    def _feature_tensors(self, model: "ATGSModel") -> list[torch.Tensor]:
        return [model.anchor_mu, model.anchor_feature, model.anchor_log_scale, model.anchor_keyframe,
                model.spatial.table, model.hash.table, model.bbox_min, model.bbox_max,
                model.anchor_velocity, model.anchor_fade]

    def _features_for(self, model: "ATGSModel") -> _Features:
        key = _key(self._feature_tensors(model))
        c = self._features
        if c is not None and _same(c.key, key):
            return c
        mu = model.anchor_mu
        xn = model.normalized_positions(mu)
        inside = ((xn >= 0) & (xn <= 1)).all(1, keepdim=True).to(mu.dtype)
        fa = model.anchor_feature
        if model.cfg.use_spatial_grid:
            fa = fa + model.spatial.query(xn, False)[0]
        partial, weights = [], []
        for lv in range(model.hash.levels):
            p, w = model.hash.spatial_slots(xn, lv)
            partial.append(p.contiguous())
            weights.append(w.contiguous())
        ls = model.anchor_log_scale
        c = _Features(key, inside, fa.contiguous(), torch.exp(ls[:, :3]), torch.exp(ls[:, 3:]),
                      partial, weights, OrderedDict(), OrderedDict())
        self._features, self._heads = c, None
        return c

    def _slice(self, model: "ATGSModel", c: _Features, m: int, lv: int, vertex: int) -> torch.Tensor:
        """Trilinear interpolation (N, F) of the time slice ``vertex`` of level lv, grid m, zero
        for anchors outside the box."""
        k = (m, lv, vertex)
        s = c.slices.get(k)
        if s is not None:
            c.slices.move_to_end(k)
            return s
        hg = model.hash
        rows = hg.combine_time(c.partial[lv], lv, vertex, m)
        feats = hg.table.index_select(0, rows.reshape(-1)).view(*rows.shape, hg.features)
        s = torch.bmm(c.weights[lv][:, None, :], feats).squeeze(1) * c.inside
        c.slices[k] = s
        per = s.numel() * s.element_size()
        keep = max(2 * hg.levels, self.slice_cache_bytes // max(per, 1))
        while len(c.slices) > keep:
            c.slices.popitem(last=False)
        return s

    def _window_for(self, model: "ATGSModel", c: _Features, f: int) -> _Window:
        k = (model.timeline.window_of_frame(f), bool(model.cfg.static_keyframe0), model.cfg.anchor_layout)  # anchor_keyframe: c.key
        w = c.windows.get(k)
        if w is not None:
            c.windows.move_to_end(k)
            return w
        active = model.active_anchors(f).nonzero().squeeze(1)
        w = _Window(active, model.anchor_mu.index_select(0, active), c.scale_off.index_select(0, active),
                    c.scale_base.index_select(0, active), None, None)
        c.windows[k] = w
        while len(c.windows) > 2:  # playback moves forward: the current and the previous window
            c.windows.popitem(last=False)
        return w

    def _heads_for(self, model: "ATGSModel", c: _Features) -> _Heads | None:
        layers = plain_heads(model.decoder)
        if layers is None:
            return None
        key = _key([p for pair in layers for lin in pair for p in (lin.weight, lin.bias)])
        h = self._heads
        if h is not None and _same(h.key, key) and h.features_key is c.key:
            return h
        d = c.fa.shape[1]
        w1 = torch.cat([a.weight for a, _ in layers]).detach()  # (H, 2D)
        b1 = torch.cat([a.bias for a, _ in layers]).detach()
        second = [(b.weight.detach().T.contiguous(), b.bias.detach()) for _, b in layers]
        h = _Heads(key, c.key, b1, w1[:, :d].T.contiguous(), w1[:, d:].T.contiguous(),
                   [a.out_features for a, _ in layers], second)
        self._heads = h
        return h

    # --- decode ---------------------------------------------------------------------------
    def decode(self, model: "ATGSModel", f: int, m: int, tau: float) -> Gaussians:
        """The Gaussians of ``model._decode(f, m, tau, None, track=False)``."""
        with self._lock, torch.no_grad():
            c = self._features_for(model)
            win = self._window_for(model, c, f)
            active, mu, scale_off, scale_base = win.active, win.mu, win.scale_off, win.scale_base
            sel = None
            if model.has_motion:  # anchor motion (atgs.model.anchor_motion), as in ATGSModel._decode
                dist, fade = model.fade_of(f, active)
                if model.cfg.temporal_fade:
                    sel = (fade >= model.fade_cut()).nonzero().squeeze(1)
                    active, mu, dist, fade = (x.index_select(0, sel) for x in (active, mu, dist, fade))
                    scale_off, scale_base = scale_off.index_select(0, sel), scale_base.index_select(0, sel)
            hg = model.hash
            parts = []
            for lv in range(hg.levels):
                v0, w0, w1 = hg.time_corners(tau, lv)
                s0 = self._slice(model, c, m, lv, v0)
                s1 = self._slice(model, c, m, lv, v0 + 1)
                parts.append(torch.add(s0.index_select(0, active) * w0, s1.index_select(0, active), alpha=w1))
            h = torch.cat(parts, dim=1)
            ft = torch.addmm(model.tmlp_b1[m], h, model.tmlp_w1[m]).relu_()
            ft = torch.addmm(model.tmlp_b2[m], ft, model.tmlp_w2[m])
            heads = self._heads_for(model, c)
            q = model.cfg.gaussians_per_anchor
            a = active.numel()
            if heads is None:  # custom decoder (e.g. reduced precision): run it as is
                fw = torch.cat([c.fa.index_select(0, active), ft], dim=1)
                raw = model.decoder(fw, mu, model.anchor_log_scale.index_select(0, active))
                opac, scales, quats, colors, means = raw.opacities, raw.scales, raw.quats, raw.colors, raw.means
            else:
                if win.pre_of is not heads:
                    win.pre, win.pre_of = torch.addmm(heads.b1, c.fa.index_select(0, win.active), heads.w_a), heads
                pre = win.pre if sel is None else win.pre.index_select(0, sel)
                hid = torch.addmm(pre, ft, heads.w_t).relu_()
                outs = [torch.addmm(b2, x, w2t) for x, (w2t, b2) in
                        zip(hid.split(heads.splits, dim=1), heads.second)]
                opac = torch.sigmoid(outs[0]).view(a, q)
                cov = outs[1].view(a, q, 7)
                scales = scale_base[:, None, :] * torch.sigmoid(cov[..., :3])
                quats = nn.functional.normalize(cov[..., 3:], dim=-1)
                colors = torch.sigmoid(outs[2]).view(a, q, 3)
                means = mu[:, None, :] + outs[3].view(a, q, 3) * scale_off[:, None, :]
            var = model.smoothing_variance()
            if var is not None:  # the 3D smoothing filter, as in ATGSModel._decode
                scales, opac = smooth(scales, opac, var.index_select(0, active))
            if model.has_motion:
                opac = opac * fade[:, None]
                if model.cfg.anchor_velocity:
                    means = means + (model.anchor_velocity.index_select(0, active) * dist[:, None])[:, None, :]
            out = [means.reshape(-1, 3), quats.reshape(-1, 4), scales.reshape(-1, 3), opac.reshape(-1),
                   colors.reshape(-1, 3)]
            keep = model.kept_gaussians(out[0], out[3])
            if keep is not None:
                out = [p.index_select(0, keep) for p in out]
            return Gaussians(*out)
