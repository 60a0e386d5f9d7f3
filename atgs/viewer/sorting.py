"""Back-to-front order of Gaussians for alpha blending, on the device the Gaussians live on.

One torch implementation for CPU and CUDA: the cull (near plane, alpha cutoff, conservative
screen-space footprint) is the view depth and four frustum-plane values of one small matrix
product plus a few elementwise tests, and the order is a
stable sort of 16-bit quantized view depths (torch's integer sort: a radix sort, linear in N,
on the CPU too). ``exact=True`` sorts the float depths instead (the reference the tests use).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from atgs.viewer.device import cpu_threads

DEPTH_LEVELS = 65535  # visible Gaussians get 16-bit keys 0..65534; 65535 marks culled ones


@dataclass(frozen=True)
class FrustumCull:
    """Image and camera for the conservative screen-space cull of :func:`back_to_front`.

    A Gaussian is dropped only if its 3-sigma footprint surely misses the image: the bound uses
    ||J||_F (with the same Jacobian clamp as the shader) times sqrt(trace Sigma3d), plus the
    0.3 px^2 dilation and the splat's half-pixel slack (the shader's triangle is larger, but
    only the ellipse inside it can write pixels).
    """

    K: np.ndarray
    width: int
    height: int
    lim: tuple[float, float, float, float]  # Jacobian clamp limits (x neg, x pos, y neg, y pos)
    scale_modifier: float = 1.0
    sigmas: float = 3.0
    dilation: float = 0.3


def view_depths(means: torch.Tensor, w2c: np.ndarray) -> torch.Tensor:
    """View-space z (OpenCV: forward) of (N,3) world points."""
    r = np.asarray(w2c, dtype=np.float64)[2]
    return _affine_rows(torch.as_tensor(means), r[None, :3], r[3:])[0]


def _affine_rows(means: torch.Tensor, A: np.ndarray, b: np.ndarray) -> torch.Tensor:
    """(k, N) rows ``A @ mean + b`` for a small (k, 3) A: one GEMM with the long dimension last.
    (BLAS handles (k,3) x (3,N) well; (N,3) x (3,k) took 6x longer with torch here, and numpy's
    float32 matmul of that shape 25x.)"""
    A_t = torch.as_tensor(A, dtype=torch.float32, device=means.device)
    b_t = torch.as_tensor(b, dtype=torch.float32, device=means.device)
    return torch.addmm(b_t[:, None], A_t, means.T)


def _cull_planes(w2c: np.ndarray, cull: FrustumCull) -> tuple[np.ndarray, np.ndarray, float]:
    """(4, 3) world-space normals, (4,) offsets and the extent factor of the four tests
    ``u + r > 0, u - r < W, v + r > 0, v - r < H`` with ``u = fx x / z + cx`` and the pixel radius
    ``r = sigmas (jf m extent / z + sqrt(dilation)) + 1``, each multiplied by z > 0 so that they
    are linear in the mean: ``n . mean + d + c extent > 0``."""
    w = np.asarray(w2c, dtype=np.float64)
    fx, fy, cx, cy = (float(cull.K[0, 0]), float(cull.K[1, 1]), float(cull.K[0, 2]), float(cull.K[1, 2]))
    lx, ly = max(cull.lim[0], cull.lim[1]), max(cull.lim[2], cull.lim[3])
    jf = math.sqrt(fx * fx * (1 + lx * lx) + fy * fy * (1 + ly * ly))
    slack = cull.sigmas * math.sqrt(cull.dilation) + 1.0
    c = cull.sigmas * jf * cull.scale_modifier
    x, y, z = w[0], w[1], w[2]  # rows: camera coordinate = row[:3] . mean + row[3]
    rows = np.stack([fx * x + (cx + slack) * z, -fx * x + (cull.width - cx + slack) * z,
                     fy * y + (cy + slack) * z, -fy * y + (cull.height - cy + slack) * z])
    return rows[:, :3], rows[:, 3], c


def back_to_front(means: torch.Tensor | np.ndarray, w2c: np.ndarray, near: float, exact: bool = False,
                  extent: torch.Tensor | np.ndarray | None = None, cull: FrustumCull | None = None,
                  opacity: torch.Tensor | np.ndarray | None = None, min_alpha: float = 0.0) -> torch.Tensor:
    """int32 indices (on the means' device) of the Gaussians in front of the near plane (and,
    with ``cull`` and ``extent``, whose footprint may touch the image; with ``opacity``, whose
    opacity reaches ``min_alpha``), farthest first.

    The opacity test is the contribution cull: a pixel's alpha is at most the opacity, and the
    shader discards alphas below ``min_alpha``, so a Gaussian with ``opacity < min_alpha``
    cannot change any pixel; dropping it here only saves its vertex and setup work."""
    means = torch.as_tensor(means)
    with cpu_threads(means.device):
        return _back_to_front(means, w2c, near, exact, extent, cull, opacity, min_alpha)


def _back_to_front(means: torch.Tensor, w2c: np.ndarray, near: float, exact: bool,
                   extent: torch.Tensor | np.ndarray | None, cull: FrustumCull | None,
                   opacity: torch.Tensor | np.ndarray | None, min_alpha: float) -> torch.Tensor:
    w = np.asarray(w2c, dtype=np.float64)
    A, b = w[2:3, :3], w[2, 3:]
    if cull is not None and extent is not None:
        normals, offsets, c = _cull_planes(w, cull)
        A, b = np.concatenate([A, normals]), np.concatenate([b, offsets])
    rows = _affine_rows(means, A, b)  # z, then the four plane tests
    z = rows[0]
    front = z > near
    if opacity is not None and min_alpha > 0.0:
        front &= torch.as_tensor(opacity) >= float(np.float32(min_alpha))
    if rows.shape[0] > 1:
        front &= rows[1:].amin(0).add_(torch.as_tensor(extent), alpha=c) > 0
    if exact:
        keep = front.nonzero().squeeze(1)
        order = torch.sort(-z[keep], stable=True).indices
        return keep[order].to(torch.int32)
    count = int(front.sum())
    if count == 0:
        return torch.zeros(0, dtype=torch.int32, device=means.device)
    zmin = float(torch.where(front, z, math.inf).amin())
    zmax = float(torch.where(front, z, -math.inf).amax())
    scale = (DEPTH_LEVELS - 1) / (zmax - zmin) if zmax > zmin else 0.0
    # 16-bit keys, shifted into int16 (torch sorts int16, not uint16): farthest -32768, nearest
    # at most 32766, culled 32767 (after every visible one, so the first `count` are the visible).
    key = (zmax - z).mul_(scale).clamp_(0.0, DEPTH_LEVELS - 1).floor_().sub_(32768.0)
    key = key.masked_fill_(~front, 32767.0).to(torch.int16)
    order = torch.sort(key, stable=True).indices[:count]
    return order.to(torch.int32)
