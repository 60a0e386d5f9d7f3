"""The torch reference rasterizer against independent checks: finite differences (float64),
the closed form of a single isotropic Gaussian, and the sequential compositing rule."""

from __future__ import annotations

import math

import pytest
import torch

from atgs.render import rasterize
from atgs.render.constants import ALPHA_MAX, ALPHA_MIN, DILATION, SIGMA_CUTOFF, T_MIN
from atgs.render.projection import project
from atgs.render.reference import rasterize_reference
from atgs.render.scenes import random_scene


def tiny_scene(n: int = 4, seed: int = 0) -> tuple[torch.Tensor, ...]:
    """A few well-separated float64 Gaussians in front of a 12x10 camera, opacities < 0.99."""
    g = torch.Generator().manual_seed(seed)
    z = 2.0 + torch.rand(n, generator=g, dtype=torch.float64)
    uv = torch.rand(n, 2, generator=g, dtype=torch.float64) * torch.tensor([8.0, 6.0]) + 2.0
    fx = 10.0
    means = torch.stack([(uv[:, 0] - 6.0) / fx * z, (uv[:, 1] - 5.0) / fx * z, z], -1)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = (0.1 + 0.2 * torch.rand(n, 3, generator=g, dtype=torch.float64)) * z[:, None] / fx
    opac = 0.3 + 0.5 * torch.rand(n, generator=g, dtype=torch.float64)
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    K = torch.tensor([[fx, 0, 6.0], [0, fx, 5.0], [0, 0, 1]], dtype=torch.float64)
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, 3] = torch.tensor([0.05, -0.03, 0.1])
    return means, quats, scales, opac, colors, viewmat, K


def test_reference_gradients_match_finite_differences() -> None:
    """Every input element: autograd vs central differences of a random linear functional."""
    means, quats, scales, opac, colors, viewmat, K = tiny_scene()
    bg = torch.tensor([0.2, 0.4, 0.1], dtype=torch.float64)
    g = torch.Generator().manual_seed(1)
    w_img, w_alpha, w_depth = (torch.randn(*s, generator=g, dtype=torch.float64) for s in ((10, 12, 3), (10, 12), (10, 12)))
    w_m2 = torch.randn(4, 2, generator=g, dtype=torch.float64)

    def loss(m, q, s, o, c) -> torch.Tensor:  # noqa: ANN001
        out = rasterize(m, q, s, o, c, viewmat, K, 12, 10, background=bg, backend="torch")
        return (out.image * w_img).sum() + (out.alpha * w_alpha).sum() + (out.depth * w_depth).sum() + (
            out.means2d * w_m2
        ).sum()

    inputs = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors)]
    grads = torch.autograd.grad(loss(*inputs), inputs)
    eps = 1e-6
    for k, (x, gk) in enumerate(zip(inputs, grads)):
        flat = x.detach().reshape(-1)
        for j in range(flat.numel()):
            plus, minus = flat.clone(), flat.clone()
            plus[j] += eps
            minus[j] -= eps
            args = [t.detach() for t in inputs]
            args[k] = plus.reshape(x.shape)
            lp = float(loss(*args))
            args[k] = minus.reshape(x.shape)
            fd = (lp - float(loss(*args))) / (2 * eps)
            assert abs(fd - float(gk.reshape(-1)[j])) <= 1e-5 * (1 + abs(fd)), (k, j, fd, float(gk.reshape(-1)[j]))
    assert all(float(gk.abs().sum()) > 0 for gk in grads)  # every input really receives gradient


def test_reference_camera_gradients_match_finite_differences() -> None:
    """viewmat (4x4) and K (3x3), differentiated only by the "torch" backend: autograd vs central
    differences in float64 for every element they use, through image, alpha, depth and means2d."""
    means, quats, scales, opac, colors, viewmat, K = tiny_scene(seed=2)
    R = torch.linalg.matrix_exp(torch.tensor([[0, -0.1, 0.05], [0.1, 0, -0.08], [-0.05, 0.08, 0]], dtype=torch.float64))
    viewmat[:3, :3] = R  # a general pose, so that every rotation entry matters
    K[0, 1] = 0.3  # skew: the projection uses the full first row
    g = torch.Generator().manual_seed(4)
    w_img, w_alpha, w_depth = (torch.randn(*s, generator=g, dtype=torch.float64) for s in ((10, 12, 3), (10, 12), (10, 12)))
    w_m2 = torch.randn(4, 2, generator=g, dtype=torch.float64)

    def loss(vm: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
        out = rasterize(means, quats, scales, opac, colors, vm, k, 12, 10, backend="torch")
        return (out.image * w_img).sum() + (out.alpha * w_alpha).sum() + (out.depth * w_depth).sum() + (
            out.means2d * w_m2
        ).sum()

    inputs = [viewmat.clone().requires_grad_(True), K.clone().requires_grad_(True)]
    grads = torch.autograd.grad(loss(*inputs), inputs)
    eps = 1e-6
    for k, (x, gk) in enumerate(zip(inputs, grads)):
        used = x.numel() - x.shape[1]  # the constant last rows ([0 0 0 1], [0 0 1]) are not read
        assert not gk[-1].any()
        for j in range(used):
            args = [t.detach().clone() for t in inputs]
            args[k].view(-1)[j] += eps
            lp = float(loss(*args))
            args[k].view(-1)[j] -= 2 * eps
            fd = (lp - float(loss(*args))) / (2 * eps)
            assert abs(fd - float(gk.view(-1)[j])) <= 1e-5 * (1 + abs(fd)), (("viewmat", "K")[k], j, fd, float(gk.view(-1)[j]))
    # the pose's rotation and translation, and fx, fy, cx, cy all receive gradient
    assert (grads[0][:3, :].abs() > 1e-6).all()
    assert all(abs(float(grads[1][i, j])) > 1e-6 for i, j in ((0, 0), (1, 1), (0, 2), (1, 2)))


def test_reference_composites_sequentially() -> None:
    """Dense torch blending equals a literal per-pixel loop written from SPEC section 2."""
    s = random_scene(40, 9, 7, seed=3, min_px=2, max_px=6, dtype=torch.float64)
    s.opacities[:10] = 1.0  # exercise the 0.99 clamp and the T stop rule
    proj = project(s.means, s.quats, s.scales, s.viewmat, s.K, 9, 7)
    bg = torch.tensor([0.3, 0.2, 0.1], dtype=torch.float64)
    img, alpha, depth, depth_sq = rasterize_reference(
        proj.means2d, proj.conics, s.opacities, s.colors, proj.depths, proj.radii, 9, 7, bg
    )
    order = [i for i in torch.argsort(proj.depths, stable=True).tolist() if proj.radii[i] > 0]
    for y in range(7):
        for x in range(9):
            T, C, D, Q = 1.0, torch.zeros(3, dtype=torch.float64), 0.0, 0.0
            for i in order:
                dx, dy = proj.means2d[i, 0] - (x + 0.5), proj.means2d[i, 1] - (y + 0.5)
                a, b, c = proj.conics[i]
                sig = float(0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy)
                if sig < 0 or sig > SIGMA_CUTOFF:
                    continue
                al = min(ALPHA_MAX, float(s.opacities[i]) * math.exp(-sig))
                if al < ALPHA_MIN:
                    continue
                if T * (1 - al) < T_MIN:
                    break
                C += s.colors[i] * al * T
                D += float(proj.depths[i]) * al * T
                Q += float(proj.depths[i]) ** 2 * al * T
                T *= 1 - al
            torch.testing.assert_close(img[y, x], C + T * bg, atol=1e-12, rtol=0)
            assert abs(float(alpha[y, x]) - (1 - T)) < 1e-12
            assert abs(float(depth[y, x]) - D) < 1e-12
            assert abs(float(depth_sq[y, x]) - Q) < 1e-12


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_single_isotropic_gaussian_closed_form(backend: str) -> None:
    """On the optical axis, alpha = o exp(-r^2 / (2 s'^2)) with s'^2 = (f s / z)^2 + 0.3."""
    W, H, f, z, s, o = 41, 33, 30.0, 2.5, 0.2, 0.8
    dtype = torch.float64 if backend == "torch" else torch.float32
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]], dtype=dtype)
    out = rasterize(
        torch.tensor([[0.0, 0.0, z]], dtype=dtype), torch.tensor([[2.0, 0, 0, 0]], dtype=dtype),
        torch.full((1, 3), s, dtype=dtype), torch.tensor([o], dtype=dtype), torch.ones(1, 3, dtype=dtype),
        torch.eye(4, dtype=dtype), K, W, H, backend=backend,
    )  # fmt: skip
    var = (f * s / z) ** 2 + DILATION
    ys, xs = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    sig = ((xs - W / 2) ** 2 + (ys - H / 2) ** 2).double() / (2 * var)
    expected = o * torch.exp(-sig)
    expected = torch.where((sig <= SIGMA_CUTOFF) & (expected >= ALPHA_MIN), expected, 0.0)
    tol = 1e-12 if backend == "torch" else 2e-6
    torch.testing.assert_close(out.alpha.double(), expected, atol=tol, rtol=0)
    torch.testing.assert_close(out.depth.double(), expected * z, atol=tol * 10, rtol=0)
    torch.testing.assert_close(out.image.double(), expected[..., None].expand(H, W, 3), atol=tol, rtol=0)
    assert out.means2d.detach().double().tolist() == [[W / 2, H / 2]]
    assert int(out.radii[0]) == math.ceil(3 * math.sqrt(var + math.sqrt(0.1)))
