"""The "cuda" backend (the gsplat wrapper, atgs/render/cuda.py) against the float64 torch
reference. Skips without a CUDA device and gsplat (CI has neither); run on a GPU machine.

gsplat cuts a splat off at up to 3.33 sigma (sqrt(2 ln(255 opacity)) sigma for faint ones) where
the reference cuts at exactly 3 sigma. A pixel between the two cut-offs has alpha = opacity * exp(-d^2 / 2) <= 0.011 *
opacity, below the shared 1/255 skip whenever opacity <= 0.35, so scenes of such splats must
agree to float32 precision; scenes of opaque splats only closely."""

from __future__ import annotations

import math

import pytest
import torch

from atgs.render import rasterize
from atgs.render.cuda import gsplat_available
from atgs.render.scenes import random_scene
from raster_checks import FIELDS, assert_mostly_close, grad_error, render_with_grads

needs_gsplat = pytest.mark.skipif(not gsplat_available(), reason="needs a CUDA device and gsplat (pip install gsplat)")

SCENES = [
    dict(n=400, width=64, height=48, seed=0),
    dict(n=250, width=37, height=71, seed=1, min_px=1.0, max_px=30.0),  # non-square, partial tiles
    dict(n=3000, width=96, height=80, seed=2, max_px=12.0),  # dense: the transmittance stop rule
]


def _faint(cfg: dict):
    """random_scene with opacities mapped from [0.05, 1] into [0.05, 0.3]."""
    scene = random_scene(**cfg)
    scene.opacities = 0.05 + (scene.opacities - 0.05) * (0.25 / 0.95)
    return scene


@needs_gsplat
@pytest.mark.parametrize("cfg", SCENES, ids=lambda c: f"{c['n']}@{c['width']}x{c['height']}")
def test_gsplat_matches_reference_where_the_cut_offs_agree(cfg: dict) -> None:
    scene = _faint(cfg)
    bg = torch.tensor([0.1, 0.5, 0.9])
    ref, gref = render_with_grads("torch", scene, torch.float64, bg)
    out, gcu = render_with_grads("cuda", scene, torch.float32, bg, device="cuda")
    assert out.backend == "cuda" and out.image.device.type == "cuda"
    assert out.image.shape == (cfg["height"], cfg["width"], 3) and out.radii.dtype == torch.int32
    assert float(ref.alpha.detach().mean()) > 0.3, "the scene covers the image"
    assert_mostly_close(out.image, ref.image, 1e-4, "image")
    assert_mostly_close(out.alpha, ref.alpha, 1e-4, "alpha")
    # depths reach 10 (depth_sq 100): a flipped 1/255 skip moves a pixel by more than 0.02 there
    assert_mostly_close(out.depth, ref.depth, 1e-3, "depth", max_diff=0.05)
    assert_mostly_close(out.depth_sq, ref.depth_sq, 1e-2, "depth_sq", max_diff=0.5)
    # gsplat's radius is ceil(extend * sigma) per axis with extend = min(3.33, sqrt(2 ln(255 opacity)))
    # (< 2.94 here), the reference's ceil(3 sigma_max): gsplat culls a few more faint splats at the
    # image border (they add nothing above 1/255, as the images above show) and never fewer
    radii, visible = out.radii.cpu(), ref.radii > 0
    assert int(((radii > 0) & ~visible).sum()) <= 2
    assert bool((radii[visible] <= ref.radii[visible] + 1).all())
    both = visible & (radii > 0)
    assert int(both.sum()) >= 0.9 * int(visible.sum())
    torch.testing.assert_close(out.means2d.detach().cpu().double()[both], ref.means2d.detach()[both],
                               atol=1e-3, rtol=1e-5)
    for name in (*FIELDS, "means2d", "background"):
        assert gcu[name] is not None, f"no gradient reaches {name}"
        assert gcu[name].device.type == "cuda" and torch.isfinite(gcu[name]).all(), name
        err = grad_error(gcu[name], gref[name])
        assert err < 1e-2, f"gradient of {name}: relative error {err:.2e}"


@needs_gsplat
def test_gsplat_is_close_to_reference_with_opaque_splats() -> None:
    """Opacities up to 1: only the pixels between the two cut-offs differ, by < 0.011 each."""
    scene = random_scene(n=600, width=64, height=64, seed=3)
    bg = torch.tensor([0.2, 0.2, 0.2])
    ref, gref = render_with_grads("torch", scene, torch.float64, bg)
    out, gcu = render_with_grads("cuda", scene, torch.float32, bg, device="cuda")
    for name in ("image", "alpha"):
        diff = getattr(out, name).detach().cpu().double() - getattr(ref, name).detach()
        psnr = -10 * math.log10(float(diff.pow(2).mean()) + 1e-20)
        assert psnr > 35, f"{name}: gsplat vs reference {psnr:.1f} dB"
    for name in ("means", "colors", "opacities", "means2d"):
        assert grad_error(gcu[name], gref[name]) < 0.15, name


@needs_gsplat
def test_auto_backend_on_cuda_tensors_is_gsplat() -> None:
    scene = random_scene(n=50, width=16, height=16, seed=4)
    params = [t.cuda() for t in scene.gaussians()]
    out = rasterize(*params, scene.viewmat.numpy(), scene.K.numpy(), 16, 16)  # numpy cameras go to the device
    assert out.backend == "cuda" and out.image.device.type == "cuda" and out.depth.device.type == "cuda"


def test_means2d_gradient_hook_copies_the_gradient_and_frees_the_graph() -> None:
    """The hook that gives the CUDA backend's (N, 2) ``means2d`` view its gradient (runs on the
    CPU: it is plain autograd). It once held the view strongly, a reference cycle through
    autograd's C++ side that kept every training step's rendering graph alive on the GPU."""
    import gc
    import weakref

    from atgs.render.cuda import forward_grad_to_view

    def step() -> tuple[weakref.ref, torch.Tensor, torch.Tensor]:
        x = torch.randn(1, 50, 2, requires_grad=True)
        base = x * 3.0  # stands in for gsplat's (1, N, 2) means2d, an autograd node
        view = base[0]
        forward_grad_to_view(base, view)
        w = torch.randn(1, 50, 2)
        (base * w).sum().backward()
        return weakref.ref(base), view.grad, w[0]

    ref, grad, expected = step()
    assert grad is not None and torch.equal(grad, expected)
    gc.collect()
    assert ref() is None, "the rendering graph outlived its step"


@needs_gsplat
def test_cuda_training_steps_do_not_accumulate_memory() -> None:
    """Repeated render + backward with the means2d gradient read, as a training step does: the
    memory allocated after step 20 equals that after step 5 (a leaked graph grows it every step)."""
    scene = random_scene(n=20000, width=128, height=96, seed=3)
    dev = torch.device("cuda")
    leaves = [t.detach().to(dev, torch.float32).requires_grad_() for t in scene.gaussians()]
    viewmat, K = scene.viewmat.to(dev, torch.float32), scene.K.to(dev, torch.float32)
    allocated = []
    for i in range(21):
        out = rasterize(*leaves, viewmat, K, scene.width, scene.height, backend="cuda")
        out.means2d.retain_grad()
        out.image.sum().backward()
        assert out.means2d.grad is not None and out.means2d.grad.shape == (20000, 2)
        for t in leaves:
            t.grad = None
        del out
        torch.cuda.synchronize()
        if i in (5, 20):
            allocated.append(torch.cuda.memory_allocated())
    assert allocated[1] <= allocated[0] + 1_000_000, allocated


@needs_gsplat
def test_gsplat_culls_at_the_near_plane_given() -> None:
    """gsplat's near_plane is the ``near`` of rasterize: a Gaussian at z = 0.1 is drawn with the
    default 0.01 and culled with 0.2, as on the CPU backends (tests/test_render_edge_cases.py)."""
    means = torch.tensor([[0.001, 0.002, 0.1], [0.01, -0.02, 1.0]], device="cuda")
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2, device="cuda")
    scales = torch.tensor([[0.0005] * 3, [0.005] * 3], device="cuda")
    opac, colors = torch.full((2,), 0.8, device="cuda"), torch.ones(2, 3, device="cuda")
    K = torch.tensor([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]], device="cuda")
    viewmat = torch.eye(4, device="cuda")
    drawn = rasterize(means, quats, scales, opac, colors, viewmat, K, 16, 12, backend="cuda").radii.tolist()
    culled = rasterize(means, quats, scales, opac, colors, viewmat, K, 16, 12, backend="cuda", near=0.2).radii.tolist()
    assert drawn[0] > 0 and culled[0] == 0
    assert drawn[1] == culled[1] > 0
