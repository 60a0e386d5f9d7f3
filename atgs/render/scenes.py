"""Random Gaussian scenes for tests and benchmarks (a camera looking down +z at a frustum)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch


@dataclass
class RandomScene:
    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor
    viewmat: torch.Tensor
    K: torch.Tensor
    width: int
    height: int

    def gaussians(self) -> tuple[torch.Tensor, ...]:
        return (self.means, self.quats, self.scales, self.opacities, self.colors)


def random_scene(
    n: int,
    width: int,
    height: int,
    seed: int = 0,
    min_px: float = 2.0,
    max_px: float = 20.0,
    depth_range: tuple[float, float] = (2.0, 10.0),
    fov_x_deg: float = 60.0,
    dtype: torch.dtype = torch.float32,
) -> RandomScene:
    """N Gaussians spread over the view frustum (10% beyond the image border).

    Each splat's 3-sigma radius on screen is log-uniform in [min_px, max_px] (per-axis
    anisotropy up to e^0.5 on top); opacities are uniform in [0.05, 1].
    """
    g = torch.Generator().manual_seed(seed)
    fx = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    K = torch.tensor([[fx, 0, width / 2], [0, fx, height / 2], [0, 0, 1]], dtype=torch.float64)
    z = torch.empty(n, dtype=torch.float64).uniform_(*depth_range, generator=g)
    u = torch.empty(n, dtype=torch.float64).uniform_(-0.1 * width, 1.1 * width, generator=g)
    v = torch.empty(n, dtype=torch.float64).uniform_(-0.1 * height, 1.1 * height, generator=g)
    means = torch.stack([(u - width / 2) / fx * z, (v - height / 2) / fx * z, z], dim=-1)
    log_r = torch.empty(n, dtype=torch.float64).uniform_(math.log(min_px), math.log(max_px), generator=g)
    sigma_px = torch.exp(log_r) / 3.0
    aniso = torch.exp(torch.empty(n, 3, dtype=torch.float64).uniform_(-0.5, 0.5, generator=g))
    scales = (sigma_px * z / fx)[:, None] * aniso
    quats = torch.randn(n, 4, dtype=torch.float64, generator=g)
    opacities = torch.empty(n, dtype=torch.float64).uniform_(0.05, 1.0, generator=g)
    colors = torch.rand(n, 3, dtype=torch.float64, generator=g)
    return RandomScene(
        *(t.to(dtype) for t in (means, quats, scales, opacities, colors)),
        viewmat=torch.eye(4, dtype=dtype), K=K.to(dtype), width=width, height=height,
    )  # fmt: skip
