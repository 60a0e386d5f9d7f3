"""Gaussian decoder F_*: four two-layer MLPs on f_w and their output activations (SPEC section 1 table).

:func:`gaussians_from_heads` turns the heads' outputs into Gaussians; the decoder's forward and
the cached inference decode (atgs.model.fast_decode, which evaluates the same heads in a
factored form) both call it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import nn

Heads = Callable[[str], torch.Tensor]
"""A head's name (GaussianDecoder.HEADS) -> its output (A, q * width) on the decoded anchors."""


def mlp(n_in: int, hidden: int, n_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(n_in, hidden), nn.ReLU(), nn.Linear(hidden, n_out))


@dataclass
class DecodedGaussians:
    """Per active anchor (A) and slot (q) Gaussian parameters."""

    means: torch.Tensor  # (A, q, 3)
    quats: torch.Tensor  # (A, q, 4) normalized (w, x, y, z)
    scales: torch.Tensor  # (A, q, 3)
    opacities: torch.Tensor  # (A, q)
    colors: torch.Tensor  # (A, q, 3)


def gaussians_from_heads(head: Heads, q: int, mu: torch.Tensor, offset_scale: torch.Tensor,
                         base_scale: torch.Tensor) -> DecodedGaussians:
    """The q Gaussians of each of A anchors at ``mu`` (A, 3) from the heads' outputs: opacity and
    colour are sigmoids, scale ``exp(v[3:]) * sigmoid(.)``, rotation the normalized quaternion,
    mean ``mu + offset * exp(v[:3])``; ``offset_scale`` = exp(v[:3]) and ``base_scale`` =
    exp(v[3:]) come as (A, 1, 3). The heads are evaluated in the order of HEADS."""
    a = mu.shape[0]
    opac = torch.sigmoid(head("opacity")).view(a, q)
    cov = head("cov").view(a, q, 7)
    scales = base_scale * torch.sigmoid(cov[..., :3])
    quats = nn.functional.normalize(cov[..., 3:], dim=-1)
    colors = torch.sigmoid(head("color")).view(a, q, 3)
    offsets = head("offset").view(a, q, 3)
    means = mu[:, None, :] + offsets * offset_scale
    return DecodedGaussians(means, quats, scales, opac, colors)


class GaussianDecoder(nn.Module):
    HEADS = ("opacity", "cov", "color", "offset")

    def __init__(self, in_dim: int, q: int, hidden_opacity: int, hidden_cov: int, hidden_color: int,
                 hidden_offset: int) -> None:
        super().__init__()
        self.q = q
        self.opacity = mlp(in_dim, hidden_opacity, q)
        self.cov = mlp(in_dim, hidden_cov, 7 * q)
        self.color = mlp(in_dim, hidden_color, 3 * q)
        self.offset = mlp(in_dim, hidden_offset, 3 * q)

    def forward(self, fw: torch.Tensor, mu: torch.Tensor, log_scale: torch.Tensor) -> DecodedGaussians:
        """Gaussians of anchors with features ``fw`` (A, 2D), positions ``mu`` and log scales v (A, 6)."""
        return gaussians_from_heads(lambda name: getattr(self, name)(fw), self.q, mu,
                                    torch.exp(log_scale[:, None, :3]), torch.exp(log_scale[:, None, 3:]))
