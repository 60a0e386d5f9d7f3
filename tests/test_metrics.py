"""Metrics against independent references: explicit-loop numpy SSIM, scipy MS-SSIM, analytic
cases and finite differences."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.signal import correlate2d

from atgs.eval import metrics as M


# --- slow references (numpy, written from the definitions) -----------------------------------------

def _gauss2d(size: int, sigma: float) -> np.ndarray:
    r = np.arange(size) - (size - 1) / 2.0
    g = np.exp(-(r**2) / (2 * sigma**2))
    g /= g.sum()
    return np.outer(g, g)


def ref_ssim_loops(x: np.ndarray, y: np.ndarray, window: np.ndarray, padding: str,
                   data_range: float = 1.0, cov_norm: float = 1.0) -> float:
    """Mean SSIM of (H,W,C) images, one window at a time."""
    k = window.shape[0]
    if padding == "same":
        p = k // 2
        x = np.pad(x, ((p, p), (p, p), (0, 0)))
        y = np.pad(y, ((p, p), (p, p), (0, 0)))
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    vals = []
    for c in range(x.shape[2]):
        for i in range(x.shape[0] - k + 1):
            for j in range(x.shape[1] - k + 1):
                wx, wy = x[i:i + k, j:j + k, c], y[i:i + k, j:j + k, c]
                mx, my = (window * wx).sum(), (window * wy).sum()
                vx = cov_norm * ((window * wx * wx).sum() - mx * mx)
                vy = cov_norm * ((window * wy * wy).sum() - my * my)
                cxy = cov_norm * ((window * wx * wy).sum() - mx * my)
                vals.append((2 * mx * my + c1) * (2 * cxy + c2) / ((mx * mx + my * my + c1) * (vx + vy + c2)))
    return float(np.mean(vals))


def ref_ms_ssim(x: np.ndarray, y: np.ndarray, levels: int, size: int = 11, sigma: float = 1.5) -> float:
    """MS-SSIM with scipy's correlate2d, per channel, weights renormalised over ``levels``."""
    w = np.array(M.MS_SSIM_WEIGHTS[:levels])
    w = w / w.sum()
    win = _gauss2d(size, sigma)
    c1, c2 = 0.01**2, 0.03**2
    per_channel = []
    for c in range(x.shape[2]):
        a, b = x[..., c], y[..., c]
        val = 1.0
        for i in range(levels):
            f = lambda im: correlate2d(im, win, mode="valid")  # noqa: E731
            ma, mb = f(a), f(b)
            va, vb, cab = f(a * a) - ma**2, f(b * b) - mb**2, f(a * b) - ma * mb
            cs = (2 * cab + c2) / (va + vb + c2)
            if i == levels - 1:
                val *= max(np.mean((2 * ma * mb + c1) / (ma**2 + mb**2 + c1) * cs), 0) ** w[i]
            else:
                val *= max(np.mean(cs), 0) ** w[i]
                a, b = _pool2(a), _pool2(b)
        per_channel.append(val)
    return float(np.mean(per_channel))


def _pool2(im: np.ndarray) -> np.ndarray:
    """Mean of 2x2 blocks; an odd side gets one zero row/column on both ends first."""
    ph, pw = im.shape[0] % 2, im.shape[1] % 2
    p = np.pad(im, ((ph, ph), (pw, pw)))
    oh, ow = (im.shape[0] + 1) // 2, (im.shape[1] + 1) // 2
    out = np.zeros((oh, ow))
    for i in range(oh):
        for j in range(ow):
            out[i, j] = p[2 * i:2 * i + 2, 2 * j:2 * j + 2].sum() / 4.0
    return out


def _pair(h: int, w: int, c: int = 3, seed: int = 0, noise: float = 0.08) -> tuple[np.ndarray, np.ndarray]:
    """A structured image (smooth gradients + edges) and a noisy, shifted copy, both in [0,1]."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    base = np.stack([0.5 + 0.4 * np.sin(6 * xx + 2 * k) * np.cos(5 * yy - k) for k in range(c)], -1)
    base[(xx * 7).astype(int) % 2 == 0] *= 0.7
    other = np.clip(np.roll(base, 1, axis=1) + noise * rng.standard_normal(base.shape), 0, 1)
    return base, other


def _t(a: np.ndarray, dtype=torch.float64) -> torch.Tensor:
    return torch.tensor(a, dtype=dtype)


# --- PSNR -------------------------------------------------------------------------------------------

def test_psnr_known_error_and_identical() -> None:
    x, _ = _pair(20, 24)
    x = 0.2 + 0.6 * x  # room for +-d without clipping
    d = 0.05
    sign = np.where(np.indices(x.shape).sum(0) % 2 == 0, 1.0, -1.0)
    y = x + d * sign  # every pixel off by exactly d: MSE = d^2
    assert float(M.psnr(_t(x), _t(y))) == pytest.approx(-20 * math.log10(d), abs=1e-9)
    assert float(M.psnr(_t(x, torch.float32), _t(y, torch.float32))) == pytest.approx(26.0206, abs=1e-3)
    assert math.isinf(float(M.psnr(_t(x), _t(x)))) and float(M.psnr(_t(x), _t(x))) > 0


def test_psnr_batched_matches_single() -> None:
    a0, b0 = _pair(16, 18, seed=1)
    a1, b1 = _pair(16, 18, seed=2, noise=0.2)
    batch = M.psnr(_t(np.stack([a0, a1])), _t(np.stack([b0, b1])))
    assert batch.shape == (2,)
    assert float(batch[0]) == pytest.approx(float(M.psnr(_t(a0), _t(b0))))
    assert float(batch[1]) == pytest.approx(float(M.psnr(_t(a1), _t(b1))))
    mse = np.mean((a1 - b1) ** 2)
    assert float(batch[1]) == pytest.approx(10 * math.log10(1 / mse), rel=1e-12)


# --- SSIM -------------------------------------------------------------------------------------------

@pytest.mark.parametrize("padding", ["same", "valid"])
def test_ssim_matches_loop_reference(padding: str) -> None:
    x, y = _pair(19, 23, c=2)
    ref = ref_ssim_loops(x, y, _gauss2d(11, 1.5), padding)
    got = float(M.ssim(_t(x), _t(y), padding=padding))
    assert got == pytest.approx(ref, abs=1e-12)
    got32 = float(M.ssim(_t(x, torch.float32), _t(y, torch.float32), padding=padding))
    assert got32 == pytest.approx(ref, abs=2e-5)
    assert 0.2 < ref < 0.95  # a meaningful, non-degenerate case


def test_ssim_identical_and_constant_analytic() -> None:
    x, _ = _pair(16, 16)
    assert float(M.ssim(_t(x), _t(x))) == pytest.approx(1.0, abs=1e-12)
    assert float(M.ms_ssim(_t(x), _t(x))) == pytest.approx(1.0, abs=1e-12)
    # constant images: variances vanish, SSIM = luminance term (2ab + C1) / (a^2 + b^2 + C1)
    a, b = 0.3, 0.7
    xa, xb = np.full((14, 15, 3), a), np.full((14, 15, 3), b)
    c1 = 0.01**2
    expect = (2 * a * b + c1) / (a * a + b * b + c1)
    assert float(M.ssim(_t(xa), _t(xb), padding="valid")) == pytest.approx(expect, abs=1e-12)


def test_ssim_batched_and_shape_errors() -> None:
    a0, b0 = _pair(15, 17, seed=3)
    a1, b1 = _pair(15, 17, seed=4, noise=0.3)
    batch = M.ssim(_t(np.stack([a0, a1])), _t(np.stack([b0, b1])))
    assert batch.shape == (2,)
    assert float(batch[1]) == pytest.approx(float(M.ssim(_t(a1), _t(b1))), abs=1e-14)
    with pytest.raises(ValueError, match="shapes differ"):
        M.ssim(_t(a0), _t(a0[:-1]))
    with pytest.raises(ValueError, match="smaller than"):
        M.ssim(_t(a0[:8]), _t(b0[:8]), padding="valid")


def test_ssim_skimage_legacy_matches_reference() -> None:
    x, y = _pair(17, 21, c=3, seed=5)
    n = 49
    ref = ref_ssim_loops(x, y, np.full((7, 7), 1 / 49), "valid", data_range=2.0, cov_norm=n / (n - 1))
    assert float(M.ssim_skimage_legacy(_t(x), _t(y))) == pytest.approx(ref, abs=1e-12)
    # data range 2 makes C1, C2 four times larger than data range 1: SSIM is higher
    assert float(M.ssim_skimage_legacy(_t(x), _t(y))) > float(M.ssim_skimage_legacy(_t(x), _t(y), data_range=1.0))


def test_ssim_gradient_finite_differences() -> None:
    """Autograd gradient vs central differences (float64) along random directions and along
    single pixels at the border, where the padding matters."""
    x, y = _pair(12, 13, c=2, seed=6)
    rng = np.random.default_rng(1)
    for padding in ("same", "valid"):
        xt = _t(x).requires_grad_(True)
        M.ssim(xt, _t(y), padding=padding).backward()
        grad = xt.grad.numpy()
        f = lambda a: float(M.ssim(_t(a), _t(y), padding=padding))  # noqa: E731
        dirs = [rng.standard_normal(x.shape) for _ in range(4)]
        for idx in [(0, 0, 0), (11, 12, 1), (5, 0, 1), (6, 7, 0)]:
            d = np.zeros_like(x)
            d[idx] = 1.0
            dirs.append(d)
        for d in dirs:
            eps = 1e-6
            fd = (f(x + eps * d) - f(x - eps * d)) / (2 * eps)
            assert float((grad * d).sum()) == pytest.approx(fd, rel=1e-5, abs=1e-9)
    # the loss direction is right: a gradient step on 1 - SSIM raises SSIM
    xt = _t(x).requires_grad_(True)
    loss = 1 - M.ssim(xt, _t(y))
    loss.backward()
    with torch.no_grad():
        better = M.ssim(xt - 0.5 * xt.grad / xt.grad.abs().max(), _t(y))
    assert better.item() > 1 - loss.item()


# --- MS-SSIM ----------------------------------------------------------------------------------------

def test_ms_ssim_levels_rule() -> None:
    assert M.ms_ssim_levels(161, 200) == 5  # 161 -> 81 -> 41 -> 21 -> 11
    assert M.ms_ssim_levels(160, 200) == 4  # 160 -> ... -> 10 < 11
    assert M.ms_ssim_levels(40, 50) == 2
    assert M.ms_ssim_levels(11, 11) == 1
    assert M.ms_ssim_levels(5, 9) == 1  # window shrinks instead


@pytest.mark.parametrize("shape,levels", [((163, 170), 5), ((43, 60), 3), ((12, 14), 1)])
def test_ms_ssim_matches_scipy_reference(shape: tuple[int, int], levels: int) -> None:
    x, y = _pair(*shape, c=2, seed=7, noise=0.1)
    assert M.ms_ssim_levels(*shape) == levels
    ref = ref_ms_ssim(x, y, levels)
    assert float(M.ms_ssim(_t(x), _t(y))) == pytest.approx(ref, abs=1e-10)


def test_ms_ssim_single_scale_is_valid_ssim_and_tiny_images() -> None:
    x, y = _pair(12, 14, seed=8)
    assert float(M.ms_ssim(_t(x), _t(y))) == pytest.approx(float(M.ssim(_t(x), _t(y), padding="valid")), abs=1e-12)
    # smaller than the window: one scale with a 7x7 Gaussian window, no crash
    xs, ys = _pair(7, 9, seed=9)
    ref = ref_ms_ssim(xs, ys, 1, size=7)
    assert float(M.ms_ssim(_t(xs), _t(ys))) == pytest.approx(ref, abs=1e-10)


def test_ms_ssim_orders_distortions() -> None:
    x, _ = _pair(64, 64, seed=10)
    rng = np.random.default_rng(0)
    small = np.clip(x + 0.02 * rng.standard_normal(x.shape), 0, 1)
    large = np.clip(x + 0.2 * rng.standard_normal(x.shape), 0, 1)
    v_small, v_large = float(M.ms_ssim(_t(x), _t(small))), float(M.ms_ssim(_t(x), _t(large)))
    assert 1.0 > v_small > v_large > 0.0
    levels = M.ms_ssim_levels(64, 64)  # both values match the slow reference, not just their order
    assert v_small == pytest.approx(ref_ms_ssim(x, small, levels), abs=1e-10)
    assert v_large == pytest.approx(ref_ms_ssim(x, large, levels), abs=1e-10)


# --- DSSIM and the bundle ---------------------------------------------------------------------------

def test_dssim_definitions_and_all_metrics() -> None:
    x, y = _pair(32, 36, seed=11)
    xt, yt = _t(x), _t(y)
    m = M.all_metrics(xt, yt)
    assert m["dssim1"] == pytest.approx((1 - float(M.ssim(xt, yt))) / 2)
    assert m["dssim1"] == pytest.approx(float(M.dssim1(xt, yt)))
    assert m["dssim2"] == pytest.approx(float(M.dssim2(xt, yt)))
    assert m["dssim_ms"] == pytest.approx(float(M.dssim_ms(xt, yt)))
    assert m["psnr"] == pytest.approx(10 * math.log10(1 / np.mean((x - y) ** 2)))
    # the render is clamped to [0,1] before scoring (as the papers' evaluation scripts do)
    over = M.all_metrics(xt + 0.5, torch.ones_like(xt))
    assert over["psnr"] == pytest.approx(float(M.psnr((xt + 0.5).clamp(0, 1), torch.ones_like(xt))))
