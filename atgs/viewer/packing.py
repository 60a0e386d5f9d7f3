"""Gaussians -> the compact vertex columns the splatting shader reads (done in the decode thread).

Per Gaussian 40 bytes in four vertex buffers (one column each, :data:`COLUMNS`):

=============  ===========================  ==========================================
column         field                        stored as
=============  ===========================  ==========================================
``mean``       mean x, y, z                 float32 (the decoded tensor itself)
``quat``       rotation w, x, y, z          int16, round(32767 q / |q|)
``scale``      scale x, y, z (std. dev.)    float32 (the decoded tensor itself)
``opacity_rgb`` opacity, r, g, b            uint16, round(65535 v) of v clamped to [0, 1]
=============  ===========================  ==========================================

The vertex shader builds the covariance from rotation and scale, so packing is two small
elementwise conversions (rotation, opacity + colour) on whatever device the decoded tensors live
on; means and scales are uploaded as decoded. On CUDA the four columns are written into one
device buffer and copied to host memory in one transfer. Why these types (measured against the
training rasterizer, docs/viewer.md): 16-bit rotations cost nothing visible (96-130 dB), half
float scales would cost ~86 dB and break for scene units below 6e-5, 8-bit colours 63-77 dB.

View-dependent colour (3DGS files): an optional fifth column of spherical-harmonic
coefficients, ``(K, 3)`` per Gaussian of degree ``sqrt(K) - 1`` in atgs.sh's order, as half
floats padded to a multiple of 4; the colour part of ``opacity_rgb`` is then unused.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from atgs.gaussians import Gaussians
from atgs.sh import sh_degree_of
from atgs.viewer.device import cpu_threads

COLUMNS = ("mean", "quat", "scale", "opacity_rgb")
COLUMN_FORMATS = ("3f4", "4i2", "3f4", "4u2")  # moderngl vertex formats of the columns
RECORD_BYTES = 40
QUAT_EPS = 1e-8  # same normalization guard as atgs.render.constants.QUAT_EPS
HALF_MAX = 65504.0


@dataclass
class PackedGaussians:
    """One frame's Gaussians ready for upload, plus what the depth sort and cull read."""

    columns: tuple[np.ndarray, ...]  # host arrays in COLUMNS order (+ SH), uploaded as they are
    means: torch.Tensor  # (N, 3) float32 on the decode device: the depth sort's input
    opacity: torch.Tensor  # (N,) float32 in [0, 1]: the alpha-cutoff cull
    extent: torch.Tensor  # (N,) sqrt(trace Sigma3d) = |scale| >= the largest std. dev.: the frustum cull
    frame: int = -1  # frame index the data belongs to (-1: not from a timeline)
    num_anchors: int = -1  # active anchors that produced it (-1: unknown)
    decode_ms: float = 0.0  # time spent decoding + packing (background thread)

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh(self) -> np.ndarray | None:
        """(N, 4 ceil(3K / 4)) float16 SH coefficients, or None for plain RGB colours."""
        return self.columns[4] if len(self.columns) > 4 else None

    @property
    def sh_degree(self) -> int:
        """Degree of the SH coefficients, -1 for plain RGB colours."""
        return -1 if self.sh is None else sh_degree_of(sh_coeffs_of_width(self.sh.shape[1]))

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def nbytes(self) -> int:
        """Memory held by this frame (host columns, device copies of the means, cull inputs)."""
        host = sum(c.nbytes for c in self.columns)
        device_means = 0 if self.device.type == "cpu" else self.means.numel() * 4
        return int(host + device_means + 4 * (self.opacity.numel() + self.extent.numel()))


def sh_width(num_coeffs: int) -> int:
    """Halves per Gaussian in the SH column: 3 K rounded up to whole vec4 attributes."""
    return 4 * -(-3 * num_coeffs // 4)


def sh_coeffs_of_width(width: int) -> int:
    """Inverse of :func:`sh_width`: the coefficient count K of an SH row of ``width`` halves."""
    for k in (1, 4, 9, 16):
        if sh_width(k) == width:
            return k
    raise ValueError(f"SH rows of {width} halves match no degree 0..3")


def row_norms(x: torch.Tensor, scratch: torch.Tensor | None = None) -> torch.Tensor:
    """(N, k) -> (N, 1) Euclidean norms of the rows: a matrix-vector product of the squares
    (torch's reductions over an inner dimension of 3-4 took 4x longer on the CPU here).
    ``scratch``: an (N, k) tensor to hold the squares (fresh 16 MB buffers cost page faults)."""
    ones = torch.ones((x.shape[1], 1), dtype=x.dtype, device=x.device)
    return torch.mm(torch.mul(x, x, out=scratch) if scratch is not None else x * x, ones).sqrt_()


def quat_column(quats: torch.Tensor) -> torch.Tensor:
    """(N,4) quaternions of any norm -> int16 round(32767 q / |q|)."""
    work = torch.empty_like(quats)
    inv = row_norms(quats, work).clamp_min_(QUAT_EPS).reciprocal_().mul_(32767.0)
    return torch.mul(quats, inv.expand_as(quats), out=work).round_().to(torch.int16)


def opacity_rgb_column(opacity: torch.Tensor, colors: torch.Tensor | None) -> torch.Tensor:
    """(N,) opacities and (N,3) colours (None: zeros) -> (N,4) uint16 of round(65535 v), v in [0, 1]."""
    n = opacity.shape[0]
    out = torch.empty((n, 4), dtype=torch.float32, device=opacity.device)
    out[:, 0] = opacity
    if colors is None:
        out[:, 1:] = 0.0
    else:
        out[:, 1:] = colors
    # int16 of v - 32768 with its sign bit flipped has the bits of the uint16 v: no uint16 kernels
    # needed (torch implements few for uint16, on CUDA even fewer).
    shifted = out.clamp_(0.0, 1.0).mul_(65535.0).round_().sub_(32768.0).to(torch.int16)
    return shifted.bitwise_xor_(-32768).view(torch.uint16)


def sh_column(coeffs: torch.Tensor) -> torch.Tensor:
    """(N, K, 3) coefficients -> (N, sh_width(K)) float16 rows (zero padded, clamped to the half range)."""
    n, k = coeffs.shape[0], coeffs.shape[1]
    sh_degree_of(k)  # validates K
    out = torch.zeros((n, sh_width(k)), dtype=torch.float16, device=coeffs.device)
    out[:, : 3 * k] = coeffs.reshape(n, 3 * k).clamp(-HALF_MAX, HALF_MAX)
    return out


def to_host(columns: list[torch.Tensor]) -> tuple[np.ndarray, ...]:
    """Host numpy arrays of the columns: views of the tensors on the CPU; on another device, one
    byte buffer filled there and copied over in a single transfer (:func:`via_one_buffer`)."""
    if all(c.device.type == "cpu" for c in columns):
        return tuple(c.contiguous().numpy() for c in columns)
    return via_one_buffer(columns)


def via_one_buffer(columns: list[torch.Tensor]) -> tuple[np.ndarray, ...]:
    """The columns concatenated as bytes on their device, copied to host memory at once, and
    split into numpy views of their dtypes and shapes (every offset stays a multiple of 4)."""
    sizes = [c.numel() * c.element_size() for c in columns]
    blob = torch.empty(sum(sizes), dtype=torch.uint8, device=columns[0].device)
    views, at = [], 0
    for c, size in zip(columns, sizes):
        blob[at : at + size] = c.contiguous().view(-1).view(torch.uint8)
        views.append((at, size, c))
        at += size
    host = blob.cpu().numpy()
    return tuple(host[a : a + s].view(_np_dtype(c.dtype)).reshape(c.shape) for a, s, c in views)


def _np_dtype(dtype: torch.dtype) -> np.dtype:
    return np.dtype({torch.float32: np.float32, torch.int16: np.int16, torch.uint16: np.uint16,
                     torch.float16: np.float16}[dtype])


def _all_finite(tensors: list[torch.Tensor]) -> bool:
    """True when every value is finite. Sums are cheaper than isfinite masks (~10x here): a NaN or
    inf makes its sum non-finite; a finite sum that overflows only sends us to the exact check."""
    sums = torch.stack([t.sum() for t in tensors])
    if bool(torch.isfinite(sums).all()):
        return True
    return all(bool(torch.isfinite(t).all()) for t in tensors)


def pack_gaussians(g: Gaussians, frame: int = -1, num_anchors: int = -1,
                   sh: torch.Tensor | None = None) -> PackedGaussians:
    """Pack Gaussians on their own device (CPU or CUDA); non-finite ones are dropped so they
    cannot poison a frame. ``sh``: optional (N, K, 3) SH coefficients (view-dependent colour,
    K = 1, 4, 9 or 16), which replace ``g.colors``. Means and scales are kept, not copied."""
    with cpu_threads(g.means.device):
        return _pack(g, frame, num_anchors, sh)


def _pack(g: Gaussians, frame: int, num_anchors: int, sh: torch.Tensor | None) -> PackedGaussians:
    n = int(g.means.reshape(-1, 3).shape[0])
    fields = [t.detach().reshape(n, k).float() for t, k in
              ((g.means, 3), (g.quats, 4), (g.scales, 3), (g.opacities, 1), (g.colors, 3))]
    if sh is not None:
        if sh.dim() != 3 or sh.shape[0] != n or sh.shape[2] != 3:
            raise ValueError(f"SH coefficients of shape {tuple(sh.shape)}: expected ({n}, K, 3)")
        fields.append(sh.detach().reshape(n, 3 * sh.shape[1]).float())
    if not _all_finite(fields):
        ok = torch.ones(n, dtype=torch.bool, device=fields[0].device)
        for t in fields:
            ok &= torch.isfinite(t).all(1)
        fields = [t[ok] for t in fields]
    means, quats, scales, op, col = (t.contiguous() for t in fields[:5])
    op = op.reshape(-1)
    columns = [means, quat_column(quats), scales, opacity_rgb_column(op, None if sh is not None else col)]
    if sh is not None:
        columns.append(sh_column(fields[5].reshape(means.shape[0], -1, 3)))
    return PackedGaussians(
        columns=to_host(columns), means=means, opacity=op.clamp(0.0, 1.0),
        extent=row_norms(scales).view(-1), frame=frame, num_anchors=num_anchors,
    )  # fmt: skip
