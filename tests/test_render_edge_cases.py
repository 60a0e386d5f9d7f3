"""Degenerate inputs on both CPU-side backends: no NaN/inf forward or backward, sane outputs."""

from __future__ import annotations

import pytest
import torch

from atgs.render import RasterInputError, rasterize

BACKENDS = ["torch", "cpu"]


def camera(width: int, height: int, f: float = 20.0) -> tuple[torch.Tensor, torch.Tensor]:
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])
    return torch.eye(4), K


def run(backend: str, means, quats, scales, opac, colors, width=16, height=12, bg=None):  # noqa: ANN001, ANN201
    """Render and back-propagate; assert every output and gradient is finite."""
    params = [torch.as_tensor(t, dtype=torch.float32).clone().requires_grad_(True)
              for t in (means, quats, scales, opac, colors)]  # fmt: skip
    viewmat, K = camera(width, height)
    out = rasterize(*params, viewmat, K, width, height, background=bg, backend=backend)
    out.means2d.retain_grad()
    g = torch.Generator().manual_seed(0)
    loss = (out.image * torch.rand(out.image.shape, generator=g)).sum() + out.alpha.sum() + out.depth.sum()
    loss.backward()
    for name, t in (("image", out.image), ("alpha", out.alpha), ("depth", out.depth), ("means2d", out.means2d)):
        assert torch.isfinite(t).all(), f"{backend}: non-finite {name}"
    for name, p in zip(("means", "quats", "scales", "opacities", "colors"), params):
        assert p.grad is not None and torch.isfinite(p.grad).all(), f"{backend}: non-finite grad of {name}"
    if out.means2d.numel():
        assert out.means2d.grad is not None and torch.isfinite(out.means2d.grad).all()
    assert out.image.shape == (height, width, 3) and out.alpha.shape == (height, width)
    assert out.radii.shape == (params[0].shape[0],) and out.radii.dtype == torch.int32
    return out, params


def gaussians(n: int, z: float = 3.0, scale: float = 0.1, opacity: float = 0.7) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(n)
    means = torch.cat([torch.rand(n, 2, generator=g) - 0.5, torch.full((n, 1), z)], dim=1)
    return [means, torch.randn(n, 4, generator=g), torch.full((n, 3), scale), torch.full((n,), opacity),
            torch.rand(n, 3, generator=g)]  # fmt: skip


@pytest.mark.parametrize("backend", BACKENDS)
def test_no_gaussians_gives_background(backend: str) -> None:
    bg = torch.tensor([0.25, 0.5, 0.75])
    out, _ = run(backend, *gaussians(0), bg=bg)
    assert torch.equal(out.image, bg.expand(12, 16, 3))
    assert not out.alpha.any() and not out.depth.any()


@pytest.mark.parametrize("backend", BACKENDS)
def test_everything_off_screen_or_behind(backend: str) -> None:
    means, q, s, o, c = gaussians(6)
    means[:, 0] = torch.tensor([50.0, -50.0, 0, 0, 0, 0])
    means[:, 1] = torch.tensor([0, 0, 50.0, -50.0, 0, 0])
    means[4:, 2] = torch.tensor([-3.0, 0.0])  # behind the camera / in its center
    bg = torch.tensor([0.1, 0.2, 0.3])
    out, params = run(backend, means, q, s, o, c, bg=bg)
    assert not out.radii.any()
    torch.testing.assert_close(out.image, bg.expand(12, 16, 3))
    assert not params[0].grad.any()


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("z", [-1.0, 0.0, 0.009, 0.01, 0.0100001, 0.011, 0.05])
def test_near_plane(backend: str, z: float) -> None:
    means, q, s, o, c = gaussians(3, z=z, scale=0.01)
    means[:, :2] *= z  # keep them inside the view frustum
    out, _ = run(backend, means, q, s, o, c)
    if z <= 0.01:
        assert not out.radii.any() and not out.alpha.any()
    else:
        assert out.radii.all()


def test_a_larger_near_plane_culls_what_the_default_draws() -> None:
    """A Gaussian at z = 0.1: drawn with the default near plane (0.01), culled with near = 0.2,
    the same way on both backends; one farther away is drawn by both near planes alike."""
    means, q, s, o, c = gaussians(2, z=0.1, scale=0.005)
    means[:, :2] *= 0.1  # inside the view frustum
    means[1] *= 10.0  # the second one at z = 1
    viewmat, K = camera(16, 12)
    outs = {}
    for backend in BACKENDS:
        for near in (0.01, 0.2):
            outs[backend, near] = rasterize(means, q, s, o, c, viewmat, K, 16, 12, backend=backend, near=near)
    for backend in BACKENDS:
        assert outs[backend, 0.01].radii.tolist()[0] > 0 and outs[backend, 0.2].radii.tolist()[0] == 0
        assert outs[backend, 0.2].radii[1] == outs[backend, 0.01].radii[1] > 0
    for near in (0.01, 0.2):
        cpu, ref = outs["cpu", near], outs["torch", near]
        assert torch.equal(cpu.radii, ref.radii)
        torch.testing.assert_close(cpu.image, ref.image, rtol=1e-4, atol=1e-5)
        torch.testing.assert_close(cpu.alpha, ref.alpha, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("near", [0.0, -0.1, float("nan"), float("inf"), True, "0.2"])
def test_a_bad_near_plane_is_refused(near: object) -> None:
    means, q, s, o, c = gaussians(1)
    viewmat, K = camera(16, 12)
    with pytest.raises(RasterInputError, match="argument 'near'"):
        rasterize(means, q, s, o, c, viewmat, K, 16, 12, backend="torch", near=near)


@pytest.mark.parametrize("backend", BACKENDS)
def test_scales_from_tiny_to_huge(backend: str) -> None:
    n = 10
    means, q, _, o, c = gaussians(n, z=2.0)
    scales = torch.logspace(-6, 3, n)[:, None].expand(n, 3).clone()
    scales[::2, 1] *= 0.5  # anisotropic too
    out, _ = run(backend, means, q, scales, o, c)
    assert out.radii[-1] > 1000  # the 1e3 splat covers everything
    assert float(out.alpha.detach().min()) > 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_flat_and_zero_quaternions(backend: str) -> None:
    means, q, s, o, c = gaussians(4)
    s[0, 2] = 0.0  # flat disc
    s[1, :2] = 0.0  # needle
    s[2] = 0.0  # point: only the 0.3 px dilation remains
    q[3] = 0.0  # zero quaternion: treated as the identity rotation
    out, params = run(backend, means, q, s, o, c)
    assert out.radii.all()
    q_id = q.clone()
    q_id[3] = torch.tensor([1.0, 0, 0, 0])
    ref, _ = run(backend, means, q_id, s, o, c)
    torch.testing.assert_close(out.image, ref.image)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("opacity", [0.0, 1.0])
def test_opacity_extremes(backend: str, opacity: float) -> None:
    out, params = run(backend, *gaussians(5, opacity=opacity, scale=0.3))
    if opacity == 0.0:
        assert not out.alpha.any()
        assert not params[4].grad.any()
    else:
        assert float(out.alpha.detach().max()) >= 0.99  # clamped at 0.99 per Gaussian, several overlap
        assert params[4].grad.abs().sum() > 0


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("size", [(1, 1), (33, 7), (5, 40), (17, 17)])
def test_odd_image_sizes(backend: str, size: tuple[int, int]) -> None:
    width, height = size
    means, q, s, o, c = gaussians(8, scale=0.5)
    out, _ = run(backend, means, q, s, o, c, width=width, height=height)
    assert float(out.alpha.detach().max()) > 0


def test_backends_agree_on_edge_cases() -> None:
    """The degenerate scenes above render the same on both backends."""
    means, q, s, o, c = gaussians(12, z=0.5, scale=0.05)
    s[0] = 0.0
    s[1] = 1e3
    q[2] = 0.0
    o[3] = 1.0
    o[4] = 0.0
    means[5, 2] = 0.01
    bg = torch.tensor([0.3, 0.6, 0.9])
    a, pa = run("torch", means, q, s, o, c, width=19, height=13, bg=bg)
    b, pb = run("cpu", means, q, s, o, c, width=19, height=13, bg=bg)
    torch.testing.assert_close(a.image, b.image, atol=2e-5, rtol=1e-4)
    torch.testing.assert_close(a.alpha, b.alpha, atol=2e-5, rtol=1e-4)
    for x, y in zip(pa, pb):
        torch.testing.assert_close(x.grad, y.grad, atol=1e-4, rtol=2e-3)
