"""The training loss of one view as a list of terms: the image loss and the regularisers, each
with its weight flag. A term with weight 0 is off (not computed); the loss is the weighted sum
of the others, in the order of :data:`LOSS_TERMS`. The functions themselves are in
:mod:`atgs.train.losses`."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
import functools
import operator
from typing import TYPE_CHECKING

import torch

from atgs.train.losses import (depth_distortion, depth_smoothness, free_space_loss, image_loss, offset_loss,
                               per_keyframe_gaussians, ray_free_space_loss, volume_loss)

if TYPE_CHECKING:
    from atgs.cameras import Camera
    from atgs.geometry.free_space import FreeSpace
    from atgs.gaussians import Gaussians
    from atgs.geometry.ray_free_space import MeasuredDepths
    from atgs.model.atgs_model import ATGSModel, Decoded
    from atgs.render.types import RasterOutput
    from atgs.train.config import TrainConfig


@dataclass(frozen=True)
class RenderedView:
    """Which view a render is: a training camera (its slot among the training cameras, at the
    training resolution), the frame, and the Gaussians it drew (after dropout)."""

    camera: "Camera"
    slot: int
    frame: int
    shown: "Gaussians"
    render: dict = field(default_factory=dict)  # further keywords of atgs.render.rasterize (the near plane)


@dataclass(frozen=True)
class LossInputs:
    """What a term reads: one rendered view, its training image and the decode it came from."""

    dec: "Decoded"
    out: "RasterOutput"
    gt: torch.Tensor
    model: "ATGSModel"
    cfg: "TrainConfig"
    free_space: "FreeSpace | None"  # None unless --train.lambda-free-space > 0
    view: "RenderedView | None" = None
    measured: "MeasuredDepths | None" = None  # None unless --train.lambda-ray-free-space > 0 and points exist


@dataclass(frozen=True)
class LossTerm:
    name: str
    weight: Callable[["TrainConfig"], float]  # from the config; 0 = off
    value: Callable[[LossInputs], "torch.Tensor | None"]  # None: nothing to compute it from


LOSS_TERMS: tuple[LossTerm, ...] = (
    # (1 - lambda_ssim) L1 + lambda_ssim (1 - SSIM): the paper's, always on
    LossTerm("image", lambda cfg: 1.0, lambda i: image_loss(i.out.image, i.gt, i.cfg.lambda_ssim)),
    LossTerm("volume", lambda cfg: cfg.lambda_volume,
             lambda i: volume_loss(i.dec.gaussians.scales, i.cfg.volume_reduction, i.model.voxel_size)),
    LossTerm("offset", lambda cfg: cfg.lambda_offset,
             lambda i: offset_loss(i.dec.offsets(i.model.anchor_mu), i.model.voxel_size, i.cfg.offset_free)),
    LossTerm("distortion", lambda cfg: cfg.lambda_distortion,
             lambda i: depth_distortion(i.out.alpha, i.out.depth, i.out.depth_sq, i.model.voxel_size)),
    LossTerm("depth_smooth", lambda cfg: cfg.lambda_depth_smooth,
             lambda i: depth_smoothness(i.out.alpha, i.out.depth, i.gt, i.cfg.depth_smooth_edge)),
    LossTerm("free_space", lambda cfg: cfg.lambda_free_space,
             lambda i: None if i.free_space is None
             else free_space_loss(i.dec.gaussians.opacities, i.dec.gaussians.means, i.free_space)),
    # the opacity each training ray accumulates in front of its measured depth (off by default)
    LossTerm("ray_free_space", lambda cfg: cfg.lambda_ray_free_space, lambda i: _ray_free_space(i)),
)


def _ray_free_space(i: LossInputs) -> "torch.Tensor | None":
    if i.measured is None or i.view is None:
        return None
    v = i.view
    moving = per_keyframe_gaussians(i.model.anchor_keyframe, i.dec.anchor_ids)
    return ray_free_space_loss(v.shown, moving, i.measured, v.slot, v.frame, v.camera, i.cfg.render_backend,
                               **v.render)


def weighted_terms(inputs: LossInputs) -> dict[str, torch.Tensor]:
    """Each active term times its weight, by name, in the order of :data:`LOSS_TERMS`."""
    terms = {}
    for term in LOSS_TERMS:
        weight = term.weight(inputs.cfg)
        if weight > 0:
            value = term.value(inputs)
            if value is not None:
                terms[term.name] = weight * value
    return terms


def total_loss(terms: dict[str, torch.Tensor]) -> torch.Tensor:
    """The sum of :func:`weighted_terms`, added in their order (the image term is always one)."""
    return functools.reduce(operator.add, terms.values())
