"""Anchor growing and pruning (Scaffold-GS style, SPEC section 1), time-conditioned.

Statistics: per Gaussian slot (anchor * q + slot) the accumulated NDC-scaled screen-space
gradient norm of its mean and how often it was rendered, and the last world position it had
(at its anchor's keyframe, without the anchor-velocity displacement);
per anchor the accumulated opacity of its q Gaussians and how often it was decoded in view.
Growing adds anchors at voxel centres (3 voxel levels) where the mean gradient is high and no
anchor of the same keyframe exists; a new anchor inherits the keyframe of its parent and the
element-wise max of its parents' features (and the mean of their velocities and fades,
atgs.model.anchor_motion). Pruning removes anchors whose mean opacity stays below a threshold;
:func:`prune_final` removes, after the last step, the anchors that never contributed since
densification stopped (never decoded in a training view, or always faint).
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import torch

from atgs.model.atgs_model import ANCHOR_TABLES, ATGSModel, Decoded
from atgs.train.config import DensifyConfig
from atgs.train.optim import SparseAdam


_PER_SLOT = ("grad_accum", "grad_count", "last_pos")  # per Gaussian slot (anchor * q + slot)
_PER_ANCHOR = ("opacity_accum", "anchor_count")
_SUMS = ("grad_accum", "grad_count", "opacity_accum", "anchor_count")  # summed over views (and workers)


@dataclass
class DensifyStats:
    """The statistics growth and pruning read. Several workers (atgs.train.distributed) move
    them as flat buffers and rows of anchors (:meth:`flat_sums`, :meth:`rows_from`): only this
    class knows its fields."""

    grad_accum: torch.Tensor  # (A*q,)
    grad_count: torch.Tensor  # (A*q,)
    last_pos: torch.Tensor  # (A*q, 3)
    opacity_accum: torch.Tensor  # (A,)
    anchor_count: torch.Tensor  # (A,)

    @classmethod
    def zeros(cls, num_anchors: int, q: int, device: torch.device | str = "cpu") -> "DensifyStats":
        n, dev = num_anchors * q, device
        return cls(torch.zeros(n, device=dev), torch.zeros(n, device=dev), torch.zeros(n, 3, device=dev),
                   torch.zeros(num_anchors, device=dev), torch.zeros(num_anchors, device=dev))

    @property
    def device(self) -> torch.device:
        return self.grad_accum.device

    @property
    def num_slots(self) -> int:
        return self.grad_accum.numel()

    @property
    def num_anchors(self) -> int:
        return self.opacity_accum.numel()

    @property
    def slots_per_anchor(self) -> int:
        return self.num_slots // max(1, self.num_anchors)

    def _rows(self, name: str, anchors: range) -> torch.Tensor:
        per = self.slots_per_anchor if name in _PER_SLOT else 1
        return getattr(self, name)[anchors.start * per:anchors.stop * per]

    # --- as buffers (several workers sum them, a checkpoint gathers them) -------------------
    def flat_sums(self, anchors: range) -> torch.Tensor:
        """The sums (everything but the last positions) of ``anchors``, as one flat buffer."""
        return torch.cat([self._rows(name, anchors).reshape(-1) for name in _SUMS])

    def restore_sums(self, anchors: range, flat: torch.Tensor) -> None:
        """Overwrite ``anchors``' sums with a buffer of :meth:`flat_sums`' layout."""
        at = 0
        with torch.no_grad():
            for name in _SUMS:
                rows = self._rows(name, anchors)
                rows.copy_(flat[at:at + rows.numel()].view_as(rows))
                at += rows.numel()

    def zero_sums(self, anchors: range) -> None:
        for name in _SUMS:
            self._rows(name, anchors).zero_()

    def positions(self, anchors: range) -> torch.Tensor:
        """(slots, 3): the last positions of ``anchors``' slots."""
        return self._rows("last_pos", anchors)

    def set_positions(self, anchors: range, positions: torch.Tensor) -> None:
        q = self.slots_per_anchor
        self.last_pos = torch.cat([self.last_pos[:anchors.start * q], positions, self.last_pos[anchors.stop * q:]])

    def rows_from(self, first_anchor: int) -> dict[str, torch.Tensor]:
        """Every field's rows of the anchors from ``first_anchor`` on, by :meth:`state_dict` name."""
        return {name: self._rows(name, range(first_anchor, self.num_anchors)) for name in self.__dataclass_fields__}

    def record(self, dec: Decoded, means2d_grad: torch.Tensor | None, radii: torch.Tensor, width: int,
               height: int, q: int) -> torch.Tensor | None:
        """Add one rendered view; returns the slots whose ``last_pos`` it wrote (None: none)."""
        self.opacity_accum.index_add_(0, dec.active, dec.raw.opacities.detach().sum(1))
        self.anchor_count.index_add_(0, dec.active, torch.ones(dec.active.numel(), device=self.device))
        if means2d_grad is None:
            return None
        # a non-finite screen-space gradient (the trainer zeroes it for the update) must not
        # poison the running sums: such Gaussians are not counted this step
        vis = ((radii > 0) & torch.isfinite(means2d_grad).all(dim=1)).nonzero().squeeze(1)
        slots = (dec.anchor_ids * q + dec.slot_ids).index_select(0, vis)  # unique: one Gaussian each
        g = means2d_grad.index_select(0, vis) * torch.tensor([0.5 * width, 0.5 * height], device=self.device)
        self.grad_accum.index_add_(0, slots, g.norm(dim=1))
        self.grad_count.index_add_(0, slots, torch.ones(slots.numel(), device=self.device))
        # at the keyframe: growth places anchors there
        self.last_pos.index_copy_(0, slots, dec.keyframe_means().index_select(0, vis))
        return slots

    def append(self, n: int, q: int) -> None:
        z = DensifyStats.zeros(n, q, self.device)
        for name in self.__dataclass_fields__:
            setattr(self, name, torch.cat([getattr(self, name), getattr(z, name)]))

    def keep(self, keep: torch.Tensor, q: int) -> None:
        """Keep the anchors of mask ``keep``, or those of indices ``keep`` in that order."""
        if keep.dtype == torch.bool:
            slot_keep = keep[:, None].expand(-1, q).reshape(-1)
        else:
            slot_keep = (keep[:, None] * q + torch.arange(q, device=keep.device)).reshape(-1)
        for name in _PER_SLOT:
            setattr(self, name, getattr(self, name)[slot_keep])
        for name in _PER_ANCHOR:
            setattr(self, name, getattr(self, name)[keep])

    def state_dict(self) -> dict:
        return {name: getattr(self, name) for name in self.__dataclass_fields__}

    @classmethod
    def from_state(cls, state: dict, device: torch.device | str = "cpu") -> "DensifyStats":
        return cls(**{k: state[k].to(device, copy=True) for k in cls.__dataclass_fields__})


def _voxel_keys(pos: torch.Tensor, keyframe: torch.Tensor, size: float) -> torch.Tensor:
    return torch.cat([keyframe[:, None], torch.round(pos / size).long()], dim=1)


def grow_anchors(model: ATGSModel, stats: DensifyStats, cfg: DensifyConfig, opt: SparseAdam | None,
                 generator: torch.Generator, growing: range | None = None, room: int | None = None) -> int:
    """Add anchors where the mean screen-space gradient is high; returns how many were added.
    ``growing``: only these anchors grow children (the generator then draws for their slots
    only); ``room``: how many may be added (default: up to ``cfg.max_anchors``)."""
    q = model.cfg.gaussians_per_anchor
    room = cfg.max_anchors - model.num_anchors if room is None else room
    min_count = cfg.interval * cfg.success_threshold * 0.5
    eligible = stats.grad_count > min_count
    if growing is not None:
        inside = torch.zeros_like(eligible)
        inside[growing.start * q:growing.stop * q] = True
        eligible &= inside
    device = stats.device
    grads = torch.where(eligible, stats.grad_accum / stats.grad_count.clamp_min(1), torch.zeros((), device=device))
    slot_anchor = torch.arange(model.num_anchors, device=device).repeat_interleave(q)
    new_mu, new_feat, new_scale, new_kf, new_vel, new_fade = [], [], [], [], [], []
    existing_kf = model.anchor_keyframe
    for i in range(cfg.levels):
        if room <= 0:
            break
        thr = cfg.grad_threshold * (cfg.hierarchy_factor // 2) ** i
        size = model.voxel_size * cfg.init_factor / cfg.hierarchy_factor**i
        cand = eligible & (grads >= thr)
        if i < cfg.levels - 1:
            cand &= grads < cfg.grad_threshold * (cfg.hierarchy_factor // 2) ** (i + 1)
        # random thinning, stronger at the finer levels (Scaffold-GS)
        # drawn where the generator lives (the trainer's CPU generator: the same draws on every device)
        if growing is None:
            draw = torch.rand(cand.shape, generator=generator, device=generator.device)
        else:
            draw = torch.zeros(cand.shape, device=generator.device)
            draw[growing.start * q:growing.stop * q] = torch.rand(len(growing) * q, generator=generator,
                                                                  device=generator.device)
        cand &= draw.to(device) > 0.5 ** (i + 1)
        idx = cand.nonzero().squeeze(1)
        if idx.numel() == 0:
            continue
        parents = slot_anchor[idx]
        keys = _voxel_keys(stats.last_pos[idx], model.anchor_keyframe[parents], size)
        old_keys = _voxel_keys(model.anchor_mu, existing_kf, size)
        allk, inv = torch.unique(torch.cat([old_keys, keys]), dim=0, return_inverse=True)
        occupied = torch.zeros(allk.shape[0], dtype=torch.bool, device=device)
        occupied[inv[: old_keys.shape[0]]] = True
        cand_inv = inv[old_keys.shape[0]:]
        free = ~occupied[cand_inv]
        if not free.any():
            continue
        ids, local = torch.unique(cand_inv[free], return_inverse=True)
        ids, local = ids[:room], local
        sel = local < ids.numel()
        n_new = ids.numel()
        feat = torch.full((n_new, model.cfg.feature_dim), -math.inf, device=device)
        feat = feat.scatter_reduce(0, local[sel, None].expand(-1, feat.shape[1]),
                                   model.anchor_feature[parents[free][sel]], reduce="amax")
        # motion: the mean of the parents' velocities and fades (they sample one moving object)
        src = parents[free][sel]
        motion = torch.cat([model.anchor_velocity[src], model.anchor_fade[src]], dim=1)
        count = torch.zeros(n_new, 1, device=device).index_add_(0, local[sel], torch.ones_like(motion[:, :1]))
        motion = torch.zeros(n_new, 4, device=device).index_add_(0, local[sel], motion) / count
        new_vel.append(motion[:, :3])
        new_fade.append(motion[:, 3:])
        key = allk[ids]
        new_mu.append(key[:, 1:].float() * size)
        new_kf.append(key[:, 0])
        new_feat.append(feat)
        new_scale.append(torch.full((n_new, 6), math.log(size), device=device))
        room -= n_new
    reset = eligible
    stats.grad_accum[reset] = 0
    stats.grad_count[reset] = 0
    if not new_mu:
        return 0
    mu, feat, scale, kf, vel, fade = (torch.cat(x) for x in (new_mu, new_feat, new_scale, new_kf, new_vel, new_fade))
    model.add_anchors(mu, feat, scale, kf, vel, fade)
    stats.append(mu.shape[0], q)
    if opt is not None:
        for name in ANCHOR_TABLES:
            opt.append_rows(name, mu.shape[0])
    return int(mu.shape[0])


def _remove_anchors(model: ATGSModel, stats: DensifyStats, prune: torch.Tensor, opt: SparseAdam | None) -> int:
    """Drop the anchors marked in ``prune`` from the model, its statistics and the optimizer
    state; never all of them. Returns how many were removed."""
    if not prune.any() or bool(prune.all()):
        return 0
    keep = ~prune
    model.keep_anchors(keep)
    stats.keep(keep, model.cfg.gaussians_per_anchor)
    if opt is not None:
        for name in ANCHOR_TABLES:
            opt.keep_rows(name, keep)
    return int(prune.sum())


def prune_anchors(model: ATGSModel, stats: DensifyStats, cfg: DensifyConfig, opt: SparseAdam | None) -> int:
    """Remove anchors seen often enough whose mean opacity (per visit, summed over q) is below
    ``min_opacity``; returns how many were removed (never all of them)."""
    seen = stats.anchor_count > cfg.interval * cfg.success_threshold
    prune = seen & (stats.opacity_accum < cfg.min_opacity * stats.anchor_count)
    stats.opacity_accum[seen] = 0
    stats.anchor_count[seen] = 0
    return _remove_anchors(model, stats, prune, opt)


def prune_final(model: ATGSModel, stats: DensifyStats, cfg: DensifyConfig, opt: SparseAdam | None,
                prune_unseen: bool) -> int:
    """After training: remove anchors whose mean opacity since the last densification is below
    ``min_opacity`` and, with ``prune_unseen`` (enough steps have passed that every anchor in
    some training view was decoded), anchors never decoded in a training view. Their Gaussians
    could only show up as untrained clutter in novel views. Returns how many were removed."""
    seen = stats.anchor_count > 0
    prune = seen & (stats.opacity_accum < cfg.min_opacity * stats.anchor_count)
    if prune_unseen:
        prune |= ~seen
    return _remove_anchors(model, stats, prune, opt)
