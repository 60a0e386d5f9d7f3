"""View-dependent colour from real spherical harmonics (SH), degree 0 to 3, in the convention
of 3D Gaussian splatting files (the `f_dc_*` / `f_rest_*` properties of a 3DGS PLY).

Coefficients are ``(..., K, 3)`` with ``K = (degree + 1)**2``, ordered by band l and, inside a
band, by m = -l..l (index ``l*l + l + m``); ``coeffs[..., 0, :]`` is the degree-0 term (f_dc).
The basis functions are the orthonormal real SH with the sign ``(-1)**m`` of the Condon-Shortley
phase kept (so band 1 is ``-C1 y, C1 z, -C1 x``), which is the convention 3DGS files are written
in. A Gaussian's colour is ``max(0.5 + sum_k coeffs_k Y_k(d), 0)`` with ``d`` the unit direction
from the camera centre to its mean (:func:`sh_colors`); the viewer's vertex shader
(atgs/shaders/splat.vert) evaluates the same polynomials.
"""

from __future__ import annotations

import torch

SH_C0 = 0.28209479177387814  # 1 / (2 sqrt(pi))
SH_C1 = 0.4886025119029199  # sqrt(3 / (4 pi))
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)
MAX_SH_DEGREE = 3


def num_sh_coeffs(degree: int) -> int:
    """K = (degree + 1)^2 coefficients per colour channel."""
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree {degree}: must be 0..{MAX_SH_DEGREE}")
    return (degree + 1) ** 2


def sh_degree_of(num_coeffs: int) -> int:
    """The degree whose coefficient count is ``num_coeffs`` (1, 4, 9 or 16)."""
    for d in range(MAX_SH_DEGREE + 1):
        if (d + 1) ** 2 == num_coeffs:
            return d
    raise ValueError(f"{num_coeffs} SH coefficients per channel: must be 1, 4, 9 or 16 (degree 0..3)")


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """(..., K) basis values at the unit directions ``dirs`` (..., 3) (normalized here)."""
    K = num_sh_coeffs(degree)
    d = torch.nn.functional.normalize(dirs, dim=-1)
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * x * z,
                SH_C2[4] * (xx - yy)]
    if degree >= 3:
        out += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * x * y * z, SH_C3[2] * y * (4 * zz - xx - yy),
                SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
                SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
    basis = torch.stack(out, -1)
    assert basis.shape[-1] == K
    return basis


def eval_sh(degree: int, coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """sum_k coeffs[..., k, :] Y_k(dirs): (..., K', 3) coefficients (K' >= K; only the first K
    are used, so higher-degree data can be evaluated at a lower degree), (..., 3) directions ->
    (..., 3). No 0.5 offset, no clamp (see :func:`sh_colors`)."""
    K = num_sh_coeffs(degree)
    if coeffs.shape[-1] != 3 or coeffs.shape[-2] < K:
        raise ValueError(f"SH coefficients of shape {tuple(coeffs.shape)}: expected (..., >= {K}, 3) for degree {degree}")
    basis = sh_basis(degree, dirs.to(coeffs.dtype))
    return (basis.unsqueeze(-1) * coeffs[..., :K, :]).sum(-2)


def sh_colors(degree: int, coeffs: torch.Tensor, means: torch.Tensor, camera_center: torch.Tensor) -> torch.Tensor:
    """(N, 3) colours of N Gaussians seen from ``camera_center`` (3,): ``max(0.5 + SH(d), 0)``
    along ``d = mean - camera_center``, as 3DGS renders them."""
    dirs = means - camera_center.to(means)
    return (eval_sh(degree, coeffs, dirs) + 0.5).clamp_min(0.0)


def rgb_to_sh0(rgb: torch.Tensor) -> torch.Tensor:
    """Degree-0 coefficient (f_dc) whose colour is ``rgb`` from every direction."""
    return (rgb - 0.5) / SH_C0


def sh0_to_rgb(dc: torch.Tensor) -> torch.Tensor:
    """Colour of a degree-0 coefficient (before the clamp at 0)."""
    return dc * SH_C0 + 0.5
