"""Gaussian decoder F_*: four two-layer MLPs on f_w (SPEC section 1 table)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn


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
        a, q = fw.shape[0], self.q
        opac = torch.sigmoid(self.opacity(fw)).view(a, q)
        cov = self.cov(fw).view(a, q, 7)
        scales = torch.exp(log_scale[:, None, 3:]) * torch.sigmoid(cov[..., :3])
        quats = nn.functional.normalize(cov[..., 3:], dim=-1)
        colors = torch.sigmoid(self.color(fw)).view(a, q, 3)
        offsets = self.offset(fw).view(a, q, 3)
        means = mu[:, None, :] + offsets * torch.exp(log_scale[:, None, :3])
        return DecodedGaussians(means, quats, scales, opac, colors)
