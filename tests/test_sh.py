"""atgs.sh against scipy's complex spherical harmonics and a quadrature of the basis."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.special import roots_legendre, sph_harm_y

from atgs.sh import eval_sh, num_sh_coeffs, rgb_to_sh0, sh0_to_rgb, sh_basis, sh_colors, sh_degree_of


def _scipy_real_sh(degree: int, dirs: np.ndarray) -> np.ndarray:
    """(N, K) real SH in the 3DGS convention from scipy's complex Y_l^m (which carries the
    Condon-Shortley phase): m < 0 -> sqrt(2) Im Y_l^|m|, m = 0 -> Y_l^0, m > 0 -> sqrt(2) Re Y_l^m."""
    d = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    polar = np.arccos(np.clip(d[:, 2], -1, 1))
    azimuth = np.arctan2(d[:, 1], d[:, 0])
    cols = []
    for l in range(degree + 1):
        for m in range(-l, l + 1):
            y = sph_harm_y(l, abs(m), polar, azimuth)
            cols.append(np.sqrt(2) * y.imag if m < 0 else (y.real if m == 0 else np.sqrt(2) * y.real))
    return np.stack(cols, 1)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_basis_matches_scipy(degree: int) -> None:
    dirs = np.random.default_rng(degree).normal(size=(500, 3)) * 2.5  # any length: normalized inside
    got = sh_basis(degree, torch.from_numpy(dirs)).numpy()
    np.testing.assert_allclose(got, _scipy_real_sh(degree, dirs), atol=1e-12)


def test_band_one_signs_are_the_3dgs_convention() -> None:
    # 3DGS files store band 1 against (-y, z, -x): a coefficient on index 3 brightens -x.
    b = sh_basis(1, torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64))
    c1 = np.sqrt(3 / (4 * np.pi))
    np.testing.assert_allclose(b[:, 1:].numpy(), [[0, 0, -c1], [-c1, 0, 0], [0, c1, 0]], atol=1e-15)


def test_basis_is_orthonormal_on_the_sphere() -> None:
    # Gauss-Legendre in cos(polar) x uniform azimuth integrates the products (degree <= 6) exactly.
    u, w = roots_legendre(8)
    az = np.arange(16) * 2 * np.pi / 16
    U, A = np.meshgrid(u, az, indexing="ij")
    s = np.sqrt(1 - U**2)
    dirs = np.stack([s * np.cos(A), s * np.sin(A), U], -1).reshape(-1, 3)
    weights = (w[:, None] * np.full(16, 2 * np.pi / 16)).reshape(-1)
    Y = sh_basis(3, torch.from_numpy(dirs)).numpy()
    gram = (Y * weights[:, None]).T @ Y
    np.testing.assert_allclose(gram, np.eye(16), atol=1e-12)


def test_eval_sh_and_colors() -> None:
    gen = torch.Generator().manual_seed(0)
    coeffs = torch.randn(50, 16, 3, generator=gen, dtype=torch.float64)
    dirs = torch.randn(50, 3, generator=gen, dtype=torch.float64)
    for degree in range(4):
        K = num_sh_coeffs(degree)
        expect = torch.einsum("nk,nkc->nc", torch.from_numpy(_scipy_real_sh(degree, dirs.numpy())), coeffs[:, :K])
        torch.testing.assert_close(eval_sh(degree, coeffs, dirs), expect)  # extra coefficients are ignored
        torch.testing.assert_close(eval_sh(degree, coeffs[:, :K], dirs), expect)
    means = torch.randn(50, 3, generator=gen, dtype=torch.float64)
    center = torch.tensor([0.3, -2.0, 1.0], dtype=torch.float64)
    col = sh_colors(3, coeffs, means, center)
    raw = eval_sh(3, coeffs, means - center) + 0.5
    assert (raw < 0).any() and (col >= 0).all()  # the clamp at 0 is exercised
    torch.testing.assert_close(col, raw.clamp_min(0))
    # degree 0 is view independent: the colour of f_dc from anywhere
    rgb = torch.rand(50, 3, generator=gen, dtype=torch.float64)
    dc = rgb_to_sh0(rgb)[:, None, :]
    torch.testing.assert_close(sh_colors(0, dc, means, center), rgb)
    torch.testing.assert_close(sh0_to_rgb(dc[:, 0]), rgb)


def test_bad_degree_and_shapes() -> None:
    assert [sh_degree_of(k) for k in (1, 4, 9, 16)] == [0, 1, 2, 3]
    with pytest.raises(ValueError, match="1, 4, 9 or 16"):
        sh_degree_of(5)
    with pytest.raises(ValueError, match="degree 4"):
        num_sh_coeffs(4)
    with pytest.raises(ValueError, match="expected"):
        eval_sh(2, torch.zeros(3, 4, 3), torch.zeros(3, 3))
