"""Back-to-front order of Gaussians for alpha blending.

The fast path quantizes view depth to 16 bits and uses numpy's stable sort, which is a radix
sort for 16-bit keys: linear in N (200k Gaussians in ~3 ms). ``exact=True`` is the float
argsort reference.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def view_depths(means: np.ndarray, w2c: np.ndarray) -> np.ndarray:
    """View-space z (OpenCV: forward) of (N,3) world points."""
    r = np.asarray(w2c, dtype=np.float32)[2]
    return means @ r[:3] + r[3]


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


def _on_screen(means: np.ndarray, extent: np.ndarray, w2c: np.ndarray, z: np.ndarray, cull: FrustumCull) -> np.ndarray:
    w = np.asarray(w2c, dtype=np.float32)
    x = means @ w[0, :3] + w[0, 3]
    y = means @ w[1, :3] + w[1, 3]
    fx, fy, cx, cy = (np.float32(v) for v in (cull.K[0, 0], cull.K[1, 1], cull.K[0, 2], cull.K[1, 2]))
    inv_z = np.float32(1.0) / z
    u = fx * x * inv_z + cx
    v = fy * y * inv_z + cy
    lx, ly = max(cull.lim[0], cull.lim[1]), max(cull.lim[2], cull.lim[3])
    jf = np.float32(np.sqrt(float(fx) ** 2 * (1 + lx * lx) + float(fy) ** 2 * (1 + ly * ly)))
    r = np.float32(cull.sigmas) * (jf * np.float32(cull.scale_modifier) * extent * inv_z
                                   + np.float32(np.sqrt(cull.dilation))) + np.float32(1.0)
    return (u + r > 0) & (u - r < cull.width) & (v + r > 0) & (v - r < cull.height)


def back_to_front(means: np.ndarray, w2c: np.ndarray, near: float, exact: bool = False,
                  extent: np.ndarray | None = None, cull: FrustumCull | None = None,
                  opacity: np.ndarray | None = None, min_alpha: float = 0.0) -> np.ndarray:
    """uint32 indices of the Gaussians in front of the near plane (and, with ``cull`` and
    ``extent``, whose footprint may touch the image; with ``opacity``, whose opacity reaches
    ``min_alpha``), farthest first.

    The opacity test is the contribution cull: a pixel's alpha is at most the opacity, and the
    shader discards alphas below ``min_alpha``, so a Gaussian with ``opacity < min_alpha``
    cannot change any pixel; dropping it here only saves its vertex and setup work."""
    z = view_depths(means, w2c)
    front = z > near
    if opacity is not None and min_alpha > 0.0:
        front &= opacity >= np.float32(min_alpha)
    if cull is not None and extent is not None:
        zs = np.where(front, z, np.float32(1.0))
        front &= _on_screen(means, extent, w2c, zs, cull)
    keep = np.flatnonzero(front).astype(np.uint32)
    if keep.size == 0:
        return keep
    zk = z[keep]
    if exact:
        return keep[np.argsort(-zk, kind="stable")]
    zmin, zmax = float(zk.min()), float(zk.max())
    if not zmax > zmin:
        return keep
    key = ((zmax - zk) * np.float32(65535.0 / (zmax - zmin))).astype(np.uint16)
    return keep[np.argsort(key, kind="stable")]
