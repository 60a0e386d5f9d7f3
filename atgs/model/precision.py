"""Reduced-precision (bfloat16 / float16) decoding: an opt-in library path for callers that trade
a little accuracy for decode speed (``atgs-view`` and evaluation decode in float32).

The four decoder MLPs (the bulk of the decode FLOPs) run in ``dtype``; the feature grids, the
per-segment temporal MLP, the output activations (sigmoid, exp, normalize) and the mean
composition ``mu + offset * exp(v)`` stay in float32, so positions keep full precision far from
the origin. The model itself is not changed: :func:`low_precision_view` returns a shallow copy
that shares every table with the model and holds a cast *copy* of the decoder.
Measured error against float32 and the tolerances: docs/model.md, section "Precision".
"""

from __future__ import annotations

import copy

import torch
from torch import nn

from atgs.gaussians import Gaussians
from atgs.model.atgs_model import ATGSModel

REDUCED_DTYPES = (torch.bfloat16, torch.float16)


class _ReducedHead(nn.Module):
    """One decoder MLP evaluated in ``dtype``; input and output stay float32."""

    def __init__(self, head: nn.Module, dtype: torch.dtype) -> None:
        super().__init__()
        self.head = copy.deepcopy(head).to(dtype)
        self.dtype = dtype

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(x.to(self.dtype)).float()


def low_precision_view(model: ATGSModel, dtype: torch.dtype = torch.bfloat16) -> ATGSModel:
    """A shallow copy of ``model`` whose decoder MLPs run in ``dtype`` (shares all tables)."""
    if dtype not in REDUCED_DTYPES:
        raise ValueError(f"low_precision_view(): argument 'dtype' is {dtype}; choose torch.bfloat16 or torch.float16")
    decoder = copy.copy(model.decoder)  # nn.Module copy: new _modules dict, original heads untouched
    decoder._modules = dict(decoder._modules)
    for name in decoder.HEADS:
        setattr(decoder, name, _ReducedHead(getattr(model.decoder, name), dtype))
    view = copy.copy(model)
    view.decoder = decoder
    return view


def gaussians_at_frame(model: ATGSModel, f: int, dtype: torch.dtype = torch.bfloat16) -> Gaussians:
    """``model.gaussians_at_frame(f)`` with the decoder MLPs in ``dtype`` (float32 output)."""
    return low_precision_view(model, dtype).gaussians_at_frame(f)


def gaussians_at(model: ATGSModel, t: float, dtype: torch.dtype = torch.bfloat16) -> Gaussians:
    """``model.gaussians_at(t)`` with the decoder MLPs in ``dtype`` (float32 output)."""
    return low_precision_view(model, dtype).gaussians_at(t)
