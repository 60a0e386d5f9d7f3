"""The compiled "cpu" backend against the torch reference: forward, gradients, projection."""

from __future__ import annotations

import pytest
import torch

from atgs.render import rasterize
from atgs.render.cpu import project_cpu
from atgs.render.projection import project
from atgs.render.scenes import random_scene
from raster_checks import FIELDS, assert_grad_close, assert_mostly_close, render_with_grads

SCENES = [
    dict(n=400, width=64, height=48, seed=0),
    dict(n=250, width=37, height=71, seed=1, min_px=1.0, max_px=30.0),  # non-square, odd tiles
    dict(n=600, width=48, height=48, seed=2, max_px=12.0),  # dense: stop rule and 0.99 clamp
]


@pytest.mark.parametrize("cfg", SCENES, ids=lambda c: f"{c['n']}@{c['width']}x{c['height']}")
def test_cpu_matches_reference(cfg: dict) -> None:
    scene = random_scene(**cfg)
    if cfg["seed"] == 2:
        scene.opacities[::3] = 1.0
    bg = torch.tensor([0.1, 0.5, 0.9])
    ref, gref = render_with_grads("torch", scene, torch.float64, bg)
    out, gcpu = render_with_grads("cpu", scene, torch.float32, bg)
    assert out.backend == "cpu" and ref.backend == "torch"
    assert out.image.dtype == torch.float32 and out.radii.dtype == torch.int32
    assert out.image.shape == (cfg["height"], cfg["width"], 3)
    assert_mostly_close(out.image, ref.image, 1e-4, "image")
    assert_mostly_close(out.alpha, ref.alpha, 1e-4, "alpha")
    assert_mostly_close(out.depth, ref.depth, 1e-3, "depth")
    assert_mostly_close(out.depth_sq, ref.depth_sq, 1e-2, "depth_sq")
    assert float((out.radii - ref.radii).abs().max()) <= 1
    torch.testing.assert_close(out.means2d.double(), ref.means2d, atol=1e-3, rtol=1e-5)
    assert float(ref.alpha.detach().mean()) > 0.3  # the scene really covers the image
    for name in (*FIELDS, "means2d", "background"):
        assert gcpu[name] is not None and gcpu[name].dtype == torch.float32, name
        assert_grad_close(gcpu[name], gref[name], name)


def test_cpu_projection_gradients_match_torch() -> None:
    """Includes Gaussians far outside the Jacobian clamp, behind the camera and on the near plane."""
    g = torch.Generator().manual_seed(5)
    n = 300
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * torch.tensor([3.0, 3.0, 1.0])
    means[:, 2] += 2.0
    means[:5, 2] = torch.tensor([-1.0, 0.0, 0.01, 0.0100001, 0.02], dtype=torch.float64)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.3
    viewmat = torch.eye(4, dtype=torch.float64)
    R, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
    viewmat[:3, :3] = R * torch.sign(torch.det(R))
    viewmat[:3, 3] = torch.tensor([0.1, 0.2, 0.3])
    means = (means - viewmat[:3, 3]) @ viewmat[:3, :3]  # keep them in front in camera space
    K = torch.tensor([[50.0, 0, 30], [0, 45, 20], [0, 0, 1]], dtype=torch.float64)
    W, H = 64, 40

    def run(fn, dtype):  # noqa: ANN001, ANN202
        ps = [t.to(dtype).clone().requires_grad_(True) for t in (means, quats, scales)]
        proj = fn(*ps, viewmat.to(dtype), K.to(dtype), W, H)
        gg = torch.Generator().manual_seed(9)
        loss = sum((t * torch.randn(t.shape, generator=gg, dtype=torch.float64).to(dtype)).sum()
                   for t in (proj.means2d, proj.conics * 100, proj.depths))  # fmt: skip
        loss.backward()
        return proj, [p.grad for p in ps]

    ref, gref = run(project, torch.float64)
    out, gcpu = run(project_cpu, torch.float32)
    in_front = ref.depths > 0.01
    lxp = (W - 30) / 50 + 0.3 * 0.5 * W / 50
    assert bool((means[in_front, 0] / means[in_front, 2] > lxp).any())  # the clamp is exercised
    torch.testing.assert_close(out.means2d.double()[in_front], ref.means2d[in_front], atol=1e-3, rtol=1e-4)
    torch.testing.assert_close(out.conics.double(), ref.conics, atol=1e-6, rtol=1e-3)
    torch.testing.assert_close(out.depths.double(), ref.depths, atol=1e-6, rtol=1e-6)
    assert int((out.radii != ref.radii).sum()) <= 2 and int((out.radii - ref.radii).abs().max()) <= 1
    assert int(out.radii[:3].abs().sum()) == 0  # behind, on and at the near plane: culled
    for name, a, b in zip(("means", "quats", "scales"), gcpu, gref):
        assert torch.isfinite(a).all()
        assert_grad_close(a, b, name, rtol=1e-4)


def test_cpu_backward_is_deterministic() -> None:
    scene = random_scene(500, 40, 40, seed=4)
    bg = torch.zeros(3)
    _, g1 = render_with_grads("cpu", scene, torch.float32, bg)
    _, g2 = render_with_grads("cpu", scene, torch.float32, bg)
    for name in g1:
        assert torch.equal(g1[name], g2[name]), name


def test_auto_picks_cpu_and_float64_inputs_work() -> None:
    scene = random_scene(50, 16, 16, seed=6, dtype=torch.float64)
    means = scene.means.clone().requires_grad_(True)
    out = rasterize(means, *scene.gaussians()[1:], scene.viewmat, scene.K, 16, 16)
    assert out.backend == "cpu" and out.image.dtype == torch.float32
    out.image.sum().backward()
    assert means.grad is not None and means.grad.dtype == torch.float64
