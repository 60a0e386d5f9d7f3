"""Learning-rate schedules (SPEC section 1): exponential decay and linear warm-up, and the rate of
every parameter group at a step (:func:`dense_lrs`, :func:`sparse_lr`). How the warm-up length
follows the run's step count is atgs.train.step_schedule's."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch

from atgs.model.anchors import STATIC
from atgs.model.atgs_model import ANCHOR_TABLES

if TYPE_CHECKING:
    from atgs.model.atgs_model import ATGSModel
    from atgs.train.config import LRConfig


def exp_decay(lr_init: float, lr_final: float, step: int, max_steps: int) -> float:
    """Log-linear interpolation from lr_init (step 0) to lr_final (step >= max_steps)."""
    if lr_init <= 0 or lr_final <= 0:
        return lr_init if step < max_steps else lr_final
    p = min(1.0, max(0.0, step / max(1, max_steps)))
    return math.exp(math.log(lr_init) * (1 - p) + math.log(lr_final) * p)


def warmup(step: int, warmup_steps: int, start: float) -> float:
    """Factor growing linearly from ``start`` to 1 over ``warmup_steps`` steps."""
    if warmup_steps <= 0 or step >= warmup_steps:
        return 1.0
    return start + (1.0 - start) * step / warmup_steps


def dense_lrs(lr: "LRConfig", step: int, iterations: int) -> dict[str, float]:
    """The decoder heads' rates at ``step`` of ``iterations``: warm-up, then log-linear decay."""
    w = warmup(step, lr.warmup_steps, lr.warmup_start)
    return {"offset": w * exp_decay(lr.offset_init, lr.offset_final, step, iterations),
            "opacity": w * exp_decay(lr.opacity_init, lr.opacity_final, step, iterations),
            "cov": w * lr.cov,
            "color": w * exp_decay(lr.color_init, lr.color_final, step, iterations)}


def sparse_lr(lr: "LRConfig", name: str, rows: torch.Tensor, step: int, model: "ATGSModel",
              grid_visits: torch.Tensor, expected_visits: int) -> float | torch.Tensor:
    """The rate of the ``rows`` of the model's sparse table ``name`` at ``step``: constant after
    warm-up, the moving anchors' tables times ``lr.moving_anchors`` (per row), and the temporal
    grids decaying each with its own visit count (``grid_visits`` of ``expected_visits``)."""
    w = warmup(step, lr.warmup_steps, lr.warmup_start)
    if lr.moving_anchors != 1.0 and name in ANCHOR_TABLES:  # per row: static anchors keep w
        moving = model.anchor_keyframe[rows] != STATIC
        w = torch.where(moving, w * lr.moving_anchors, w).float()
    if name == "anchor_feature":
        return w * lr.anchor_feature
    if name == "anchor_log_scale":
        return w * lr.anchor_scaling
    if name == "spatial":
        return w * lr.spatial_grid
    if name == "anchor_velocity":
        return w * lr.anchor_velocity * model.extent
    if name == "anchor_fade":
        return w * lr.anchor_fade
    # temporal grids: each decays with its own visit count
    # (one rate per grid, then one per row: the hash tables have ~10^5 rows a step)
    p = (grid_visits.double() / expected_visits).clamp(0, 1)
    if name == "hash":
        a, b = lr.temporal_init * model.extent, lr.temporal_final * model.extent
    else:
        a, b = lr.temporal_mlp_init, lr.temporal_mlp_final
    per_grid = (w * torch.exp(math.log(a) * (1 - p) + math.log(b) * p)).float()
    return per_grid[rows // (model.hash.levels * model.hash.table_size) if name == "hash" else rows]
