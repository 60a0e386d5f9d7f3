"""Result type of :func:`atgs.render.rasterize`."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class RasterOutput:
    """Rendered image and per-Gaussian screen-space data.

    ``depth`` is the alpha-weighted view depth ``sum_i alpha_i T_i z_i`` (NOT divided by
    ``alpha``; divide by ``alpha.clamp_min(eps)`` for an expected depth of the covered part), and
    ``depth_sq`` the same sum of ``z_i^2``: with them ``alpha * depth_sq - depth^2`` is the
    spread of the depths along each ray (atgs.train.losses.depth_distortion).
    ``means2d`` is a node of the autograd graph: call ``out.means2d.retain_grad()`` before
    ``backward()`` to read the screen-space mean gradient. ``radii`` is 0 for culled Gaussians.
    """

    image: torch.Tensor  # (H, W, 3)
    alpha: torch.Tensor  # (H, W) 1 - final transmittance
    depth: torch.Tensor  # (H, W)
    depth_sq: torch.Tensor  # (H, W)
    means2d: torch.Tensor  # (N, 2) pixel coordinates, pixel centers at +0.5
    radii: torch.Tensor  # (N,) int32 3-sigma radius in pixels, 0 = culled
    backend: str = ""  # the backend that produced this output
