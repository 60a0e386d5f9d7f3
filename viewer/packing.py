"""Gaussians -> the GPU layout of the splatting shader (done in the decode thread, not the UI).

Per Gaussian 12 uint32 words = 3 RGBA32UI texels:
``(mean.xyz, opacity) | (cov00, cov01, cov02, cov11) | (cov12, cov22, r|g<<16, b)`` with floats
stored as their bit patterns (an integer texture passes them through untouched) and colors as
16-bit unorm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from atgs.gaussians import Gaussians

WORDS_PER_GAUSSIAN = 12
QUAT_EPS = 1e-8  # same normalization guard as atgs.render.constants.QUAT_EPS


@dataclass
class PackedGaussians:
    """One frame's Gaussians ready for upload."""

    data: np.ndarray  # (N, 12) uint32
    means: np.ndarray  # (N, 3) float32, for the depth sort
    frame: int = -1  # frame index the data belongs to (-1: not from a timeline)
    num_anchors: int = -1  # active anchors that produced it (-1: unknown)
    decode_ms: float = 0.0  # time spent decoding + packing (background thread)
    extent: np.ndarray | None = None  # (N,) sqrt(trace Sigma3d) >= largest std dev (for culling)

    def __post_init__(self) -> None:
        if self.extent is None:
            cov = self.data[:, 4:10].view(np.float32)
            self.extent = np.sqrt(np.maximum(cov[:, 0] + cov[:, 3] + cov[:, 5], 0.0)).astype(np.float32)

    def __len__(self) -> int:
        return int(self.data.shape[0])


def covariances(quats: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """(N,4) wxyz quaternions (any norm) and (N,3) standard deviations -> (N,6) float32 upper
    triangle (00, 01, 02, 11, 12, 22) of R S S^T R^T. Plain 1-D numpy in float32: linear in N."""
    q = np.asarray(quats, dtype=np.float32)
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), np.float32(QUAT_EPS))
    w, x, y, z = (np.ascontiguousarray(q[:, k]) for k in range(4))
    s = np.asarray(scales, dtype=np.float32)
    s0, s1, s2 = (np.ascontiguousarray(s[:, k]) for k in range(3))
    # Rows of M = R S: M[a][j] = R[a][j] * s_j.
    M = (
        ((1 - 2 * (y * y + z * z)) * s0, 2 * (x * y - w * z) * s1, 2 * (x * z + w * y) * s2),
        (2 * (x * y + w * z) * s0, (1 - 2 * (x * x + z * z)) * s1, 2 * (y * z - w * x) * s2),
        (2 * (x * z - w * y) * s0, 2 * (y * z + w * x) * s1, (1 - 2 * (x * x + y * y)) * s2),
    )
    out = np.empty((q.shape[0], 6), dtype=np.float32)
    for k, (i, j) in enumerate(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))):
        out[:, k] = M[i][0] * M[j][0] + M[i][1] * M[j][1] + M[i][2] * M[j][2]
    return out


def _np(t: torch.Tensor | np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    if isinstance(t, torch.Tensor):
        t = t.detach().to("cpu", torch.float32).numpy()
    return np.asarray(t, dtype=np.float32).reshape(shape)


def pack_gaussians(g: Gaussians, frame: int = -1, num_anchors: int = -1) -> PackedGaussians:
    """Pack (CPU) Gaussians; non-finite Gaussians are dropped so they cannot poison a frame."""
    means = _np(g.means, (-1, 3))
    n = means.shape[0]
    quats, scales = _np(g.quats, (n, 4)), _np(g.scales, (n, 3))
    op, col = _np(g.opacities, (n,)), _np(g.colors, (n, 3))
    # One flat check first (per-row reductions over 3-4 columns cost more than the packing).
    if not all(bool(np.isfinite(a).all()) for a in (means, quats, scales, op, col)):
        ok = np.isfinite(means).all(1) & np.isfinite(quats).all(1) & np.isfinite(scales).all(1)
        ok &= np.isfinite(op) & np.isfinite(col).all(1)
        means, quats, scales, op, col = means[ok], quats[ok], scales[ok], op[ok], col[ok]
        n = means.shape[0]
    f = np.empty((n, WORDS_PER_GAUSSIAN), dtype=np.float32)
    f[:, 0:3] = means
    f[:, 3] = np.clip(op, 0.0, 1.0)
    f[:, 4:10] = covariances(quats, scales)
    data = f.view(np.uint32)
    c16 = np.rint(np.clip(col, 0.0, 1.0) * 65535.0).astype(np.uint32)
    data[:, 10] = c16[:, 0] | (c16[:, 1] << 16)
    data[:, 11] = c16[:, 2]
    return PackedGaussians(data=data, means=np.ascontiguousarray(means), frame=frame, num_anchors=num_anchors)
