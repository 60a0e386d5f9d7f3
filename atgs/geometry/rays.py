"""Rays through a camera's pixels, in its camera frame: the inverse of the pinhole.

A ray through pixel position (u, v) is [(u - cx) / fx, (v - cy) / fy, 1]: the camera-frame
point at depth z on it is the ray times z, and ``(ray * z - t) @ R`` the world point
(:func:`to_world`). Every user builds its rays here: the seen-space samples, the stereo's depth
ranges and view scores, the surface extension, the fusion's cross-checks and the oracle points.
"""

from __future__ import annotations

import numpy as np
import torch

from atgs.cameras import Camera


def pixel_rays(cam: Camera, u: np.ndarray | torch.Tensor, v: np.ndarray | torch.Tensor, dim: int = -1,
               inverse_intrinsics: bool = False) -> np.ndarray | torch.Tensor:
    """Camera-frame rays [(u - cx) / fx, (v - cy) / fy, 1] through the pixel positions (u, v)
    (arrays or tensors, (N,)), stacked along ``dim`` ((N, 3) for -1, (3, N) for 0).

    ``inverse_intrinsics`` (tensors only): the rays as the product K^-1 [u, v, 1], as the stereo's
    fusion has always built them. The two agree to the last bits only mostly (the inverse's
    entries are rounded on their own); the fused points of atgs-prepare depend on them, so both
    ways stay, each where it was."""
    if inverse_intrinsics:
        pix = torch.stack([u, v, torch.ones_like(u)])
        rays = torch.linalg.inv(torch.from_numpy(cam.K).to(u.dtype)) @ pix
        return rays if dim == 0 else rays.movedim(0, dim)
    x, y = (u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy
    if isinstance(x, torch.Tensor):
        return torch.stack([x, y, torch.ones_like(x)], dim)
    return np.stack([x, y, np.ones_like(x)], dim)


def pixel_centres(cam: Camera) -> tuple[torch.Tensor, torch.Tensor]:
    """(H*W,) float64 tensors u, v of every pixel centre of ``cam``, row-major."""
    v, u = torch.meshgrid(torch.arange(cam.height, dtype=torch.float64) + 0.5,
                          torch.arange(cam.width, dtype=torch.float64) + 0.5, indexing="ij")
    return u.reshape(-1), v.reshape(-1)


def grid_rays(cam: Camera, n_side: int) -> np.ndarray:
    """(n_side^2, 3) rays through the centres of an n_side x n_side grid of cells over the image."""
    u = (np.arange(n_side) + 0.5) / n_side * cam.width
    v = (np.arange(n_side) + 0.5) / n_side * cam.height
    U, V = np.meshgrid(u, v)
    return pixel_rays(cam, U.ravel(), V.ravel())


def to_world(cam: Camera, pc: np.ndarray) -> np.ndarray:
    """Camera-frame points (N, 3) -> world points (N, 3)."""
    return (pc - cam.t) @ cam.R
