"""Helpers shared by the rasterizer backend tests (tests/test_render_cpu.py, test_render_cuda.py):
render with gradients of a fixed random functional, and compare against the torch reference."""

from __future__ import annotations

import torch

from atgs.render import rasterize

FIELDS = ("means", "quats", "scales", "opacities", "colors")


def render_with_grads(backend: str, scene, dtype: torch.dtype, bg: torch.Tensor, seed: int = 7,
                      device: str = "cpu"):
    """Render on ``device``, back-propagate a fixed random functional of image/alpha/depth/depth_sq
    (the same weights on every device: drawn on the CPU), return the output and all gradients."""
    params = [t.detach().to(device=device, dtype=dtype).clone().requires_grad_(True) for t in scene.gaussians()]
    bgp = bg.to(device=device, dtype=dtype).clone().requires_grad_(True)
    out = rasterize(*params, scene.viewmat.to(device=device, dtype=dtype), scene.K.to(device=device, dtype=dtype),
                    scene.width, scene.height, background=bgp, backend=backend)  # fmt: skip
    out.means2d.retain_grad()
    g = torch.Generator().manual_seed(seed)
    H, W = scene.height, scene.width
    w_img, w_alpha, w_depth, w_sq = (torch.randn(s, generator=g, dtype=torch.float64).to(device=device, dtype=dtype)
                                     for s in ((H, W, 3), (H, W), (H, W), (H, W)))
    loss = ((out.image * w_img).sum() + (out.alpha * w_alpha).sum() + (out.depth * w_depth).sum() * 0.1
            + (out.depth_sq * w_sq).sum() * 0.01)
    loss.backward()
    grads = {name: p.grad for name, p in zip(FIELDS, params)}
    grads["means2d"] = out.means2d.grad
    grads["background"] = bgp.grad
    return out, grads


def assert_mostly_close(a: torch.Tensor, b: torch.Tensor, atol: float, name: str, max_fraction: float = 0.002,
                        max_diff: float = 0.02) -> None:
    """Element-wise close except for a tiny fraction of pixels where a float32 rounding flips a
    discrete decision (the 1/255 skip or the 3-sigma cut) between the two implementations."""
    diff = (a.detach().cpu().double() - b.detach().cpu().double()).abs()
    bad = float((diff > atol).double().mean())
    assert bad <= max_fraction, f"{name}: {bad:.3%} of elements differ by more than {atol}"
    assert float(diff.max()) < max_diff, f"{name}: max difference {float(diff.max())}"


def grad_error(a: torch.Tensor, b: torch.Tensor) -> float:
    """Relative error of a whole gradient tensor against a reference one."""
    a, b = a.detach().cpu().double(), b.detach().cpu().double()
    return float((a - b).norm() / b.norm().clamp_min(1e-12))


def assert_grad_close(a: torch.Tensor, b: torch.Tensor, name: str, rtol: float = 2e-3) -> None:
    """Relative error of the whole gradient tensor (float32 kernel vs float64 reference)."""
    err = grad_error(a, b)
    assert err < rtol, f"gradient of {name}: relative error {err:.2e}"
