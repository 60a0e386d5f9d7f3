"""A set of 3D Gaussians as the rasterizer and the viewer take them."""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch


@dataclass
class Gaussians:
    """N Gaussians. ``quats`` are (w, x, y, z), not necessarily normalized; ``scales`` are linear
    standard deviations; ``opacities`` in [0, 1]; ``colors`` linear RGB in [0, 1]."""

    means: torch.Tensor  # (N, 3)
    quats: torch.Tensor  # (N, 4)
    scales: torch.Tensor  # (N, 3)
    opacities: torch.Tensor  # (N,)
    colors: torch.Tensor  # (N, 3)

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def map(self, fn) -> "Gaussians":
        return Gaussians(**{f.name: fn(getattr(self, f.name)) for f in fields(self)})

    def to(self, *args, **kwargs) -> "Gaussians":
        return self.map(lambda x: x.to(*args, **kwargs))

    def detach(self) -> "Gaussians":
        return self.map(lambda x: x.detach())

    @staticmethod
    def cat(parts: list["Gaussians"]) -> "Gaussians":
        return Gaussians(**{f.name: torch.cat([getattr(p, f.name) for p in parts]) for f in fields(Gaussians)})

    def as_tuple(self) -> tuple[torch.Tensor, ...]:
        return (self.means, self.quats, self.scales, self.opacities, self.colors)
