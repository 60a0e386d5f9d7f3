"""The inference decode's gather (``gaussians_at`` / ``gaussians_at_frame``: no autograd, no
camera): each decoded anchor's inputs to the decoder heads and the heads' outputs, from caches.

Both decodes share everything after the heads (ATGSModel._drawn: smoothing, fade, velocity, the
kept-Gaussians cut) and the heads' activations (atgs.model.decoder.gaussians_from_heads); what
differs is how they gather. Training reads the rows of the anchors it decodes as autograd
leaves, every step anew. Here only the local time tau changes between frames, so everything that
depends on the anchors alone is computed once per parameter state and kept:

- per anchor: ``inside``, ``exp(v)``, ``f_a + f_s`` and the spatial part of every hash level's
  corner slots with its trilinear weights;
- per keyframe window (the last two): the active anchors, their rows of the above, and their
  ``f_a + f_s`` times that half of the four decoder heads' first layers (stacked into one
  matrix, biases included);
- per (segment, level, time vertex) of the 4D hash grid: the trilinear spatial interpolation of
  that time slice for every anchor (the 4D quadrilinear interpolation is the time-weighted sum
  of two such slices), built lazily and kept in a memory-bounded LRU.

A frame then costs two cached slices per level, the small per-segment MLP, one matmul for the
time half of the stacked first layers, and the four heads' second layers. The cache reads only
:class:`DecodeTables` (it knows nothing else of the model) and is keyed on the identity and
in-place version counter (``Tensor._version``) of every tensor it was built from, so a
checkpoint load, an optimizer step (in-place ``index_copy_`` / Adam) or an anchor edit (new
tensors) invalidates it. Results equal the training decode up to float32 summation order;
tests/test_model_decode_speed_equivalence.py checks this, and tests/test_model_decode_reference.py
checks both decodes against a float64 reference.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
import threading

import torch
from torch import nn

from atgs.model.decoder import DecodedGaussians, GaussianDecoder, gaussians_from_heads
from atgs.model.grids import HashGrid4D, SpatialGrid

# Bytes of hash-slice cache kept per model (at least two slices per level are always kept).
SLICE_CACHE_BYTES = 256 * 2**20


@dataclass(frozen=True)
class DecodeTables:
    """What the inference decode reads of a model (ATGSModel builds it for each decode)."""

    mu: torch.Tensor  # (N, 3) anchor positions
    keyframe: torch.Tensor  # (N,) anchor keyframes (they decide each window's anchors)
    feature: torch.Tensor  # (N, D) f_a
    log_scale: torch.Tensor  # (N, 6) v
    bbox_min: torch.Tensor  # the grids' box, through ``normalized``
    bbox_max: torch.Tensor
    normalized: Callable[[torch.Tensor], torch.Tensor]  # positions -> grid coordinates in [0, 1]^3
    spatial: SpatialGrid | None  # F_s (None: off)
    hash: HashGrid4D
    temporal_mlp: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]  # w1, b1, w2, b2 per segment
    decoder: nn.Module
    q: int  # Gaussians per anchor

    def anchor_tensors(self) -> list[torch.Tensor]:
        """The tensors the per-anchor cache is built from."""
        grids = [self.hash.table] + ([self.spatial.table] if self.spatial is not None else [])
        return [self.mu, self.keyframe, self.feature, self.log_scale, self.bbox_min, self.bbox_max, *grids]


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
    slot_of: "OrderedDict[tuple[int, int, int], int]"  # (m, level, vertex) -> its slot in ``pool``, LRU order
    windows: "OrderedDict[Hashable, Window]"  # keyframe window -> its active anchors' rows
    pool: torch.Tensor | None = None  # (slots, N, F): the cached time slices, allocated once
    free: list[int] = field(default_factory=list)  # slots of ``pool`` not in use


@dataclass
class Window:
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


def slice_slots(hg: HashGrid4D, slice_bytes: int, budget_bytes: int) -> int:
    """Slots of the slice cache: what ``budget_bytes`` holds, but no more than the slices there
    are (grid, level, time vertex) and at least 2 x levels. (Without the cap a model with no
    anchor, its slices 0 bytes, asked for 256 Mi slots: an 11 GB list of free slots.)"""
    slices = hg.num_grids * sum(r + 1 for r in hg.time_res)  # (a level of time resolution r: vertices 0..r)
    return max(2 * hg.levels, min(slices, budget_bytes // max(slice_bytes, 1)))


class InferenceCache:
    """Per-model cache of the time-invariant decode quantities. A decode holds ``lock`` from
    :meth:`window` to the end of its use of :meth:`gather`'s result (thread safe)."""

    def __init__(self, slice_cache_bytes: int = SLICE_CACHE_BYTES) -> None:
        self.slice_cache_bytes = int(slice_cache_bytes)
        self.lock = threading.Lock()
        self._features: _Features | None = None
        self._heads: _Heads | None = None

    def clear(self) -> None:
        with self.lock:
            self._features, self._heads = None, None

    # --- cached quantities -------------------------------------------------------------------
    def _features_for(self, t: DecodeTables) -> _Features:
        key = _key(t.anchor_tensors())
        c = self._features
        if c is not None and _same(c.key, key):
            return c
        xn = t.normalized(t.mu)
        inside = ((xn >= 0) & (xn <= 1)).all(1, keepdim=True).to(t.mu.dtype)
        fa = t.feature
        if t.spatial is not None:
            fa = fa + t.spatial.query(xn, False)[0]
        partial, weights = [], []
        for lv in range(t.hash.levels):
            p, w = t.hash.spatial_slots(xn, lv)
            partial.append(p.contiguous())
            weights.append(w.contiguous())
        ls = t.log_scale
        c = _Features(key, inside, fa.contiguous(), torch.exp(ls[:, :3]), torch.exp(ls[:, 3:]),
                      partial, weights, OrderedDict(), OrderedDict())
        self._features, self._heads = c, None
        return c

    def _slice(self, hg: HashGrid4D, c: _Features, m: int, lv: int, vertex: int) -> torch.Tensor:
        """Trilinear interpolation (N, F) of the time slice ``vertex`` of level lv, grid m, zero
        for anchors outside the box. Cached in one pool of slots allocated once (at most
        ``slice_cache_bytes``, least recently used slot reused): as separate tensors, a long
        playback left the slices scattered between the decode's passing allocations and the
        process's heap grew far past the cache (1.2 GB for 140 MB of slices, 300 frames);
        at least 2 x levels slots, so that a decode's own slices are never reused under it, and
        no more than there are slices (:func:`slice_slots`)."""
        k = (m, lv, vertex)
        slot = c.slot_of.get(k)
        if slot is not None:
            c.slot_of.move_to_end(k)
            return c.pool[slot]
        rows = hg.combine_time(c.partial[lv], lv, vertex, m)
        feats = hg.table.index_select(0, rows.reshape(-1)).view(*rows.shape, hg.features)
        s = torch.bmm(c.weights[lv][:, None, :], feats).squeeze(1) * c.inside
        if c.pool is None:
            keep = slice_slots(hg, s.numel() * s.element_size(), self.slice_cache_bytes)
            c.pool, c.free = s.new_empty((keep, *s.shape)), list(range(keep - 1, -1, -1))
        if not c.free:
            c.free.append(c.slot_of.popitem(last=False)[1])
        slot = c.free.pop()
        c.pool[slot].copy_(s)
        c.slot_of[k] = slot
        return c.pool[slot]

    def _heads_for(self, decoder: nn.Module, c: _Features) -> _Heads | None:
        layers = plain_heads(decoder)
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

    # --- the gather ------------------------------------------------------------------------------
    def window(self, t: DecodeTables, key: Hashable, active_ids: Callable[[], torch.Tensor]) -> Window:
        """The cached rows of the anchors of keyframe window ``key`` (``active_ids()``: their ids,
        asked for when the window is not cached)."""
        c = self._features_for(t)
        w = c.windows.get(key)
        if w is not None:
            c.windows.move_to_end(key)
            return w
        active = active_ids()
        w = Window(active, t.mu.index_select(0, active), c.scale_off.index_select(0, active),
                   c.scale_base.index_select(0, active), None, None)
        c.windows[key] = w
        while len(c.windows) > 2:  # playback moves forward: the current and the previous window
            c.windows.popitem(last=False)
        return w

    def gather(self, t: DecodeTables, win: Window, shown: torch.Tensor | None, m: int, tau: float
               ) -> tuple[torch.Tensor, DecodedGaussians]:
        """(ids, Gaussians as the decoder heads give them) of the anchors of ``win`` at rows
        ``shown`` (None: all) in segment m at local time tau."""
        c = self._features_for(t)
        pick = (lambda x: x) if shown is None else (lambda x: x.index_select(0, shown))
        active, mu, scale_off, scale_base = (pick(x) for x in (win.active, win.mu, win.scale_off, win.scale_base))
        hg = t.hash
        parts = []
        for lv in range(hg.levels):
            v0, w0, w1 = hg.time_corners(tau, lv)
            s0 = self._slice(hg, c, m, lv, v0)
            s1 = self._slice(hg, c, m, lv, v0 + 1)
            parts.append(torch.add(s0.index_select(0, active) * w0, s1.index_select(0, active), alpha=w1))
        h = torch.cat(parts, dim=1)
        tw1, tb1, tw2, tb2 = t.temporal_mlp
        ft = torch.addmm(tb1[m], h, tw1[m]).relu_()
        ft = torch.addmm(tb2[m], ft, tw2[m])
        heads = self._heads_for(t.decoder, c)
        if heads is None:  # custom decoder (e.g. reduced precision): run it as is
            fw = torch.cat([c.fa.index_select(0, active), ft], dim=1)
            return active, t.decoder(fw, mu, t.log_scale.index_select(0, active))
        if win.pre_of is not heads:
            win.pre, win.pre_of = torch.addmm(heads.b1, c.fa.index_select(0, win.active), heads.w_a), heads
        hid = torch.addmm(pick(win.pre), ft, heads.w_t).relu_()
        outs = dict(zip(GaussianDecoder.HEADS, (torch.addmm(b2, x, w2t) for x, (w2t, b2) in
                                                zip(hid.split(heads.splits, dim=1), heads.second))))
        return active, gaussians_from_heads(outs.__getitem__, t.q, mu, scale_off[:, None, :], scale_base[:, None, :])
