"""Optional GPU backend: a thin wrapper over gsplat's ``rasterization``.

Tested against the float64 torch reference by tests/test_render_cuda.py, which needs a GPU (CI has
none; last run on an NVIDIA H200 with gsplat 1.5.3). Numerics differ slightly from the CPU
backends: gsplat cuts a splat at min(3.33, sqrt(2 ln(255 opacity))) sigma per axis instead of the
exact 3-sigma ellipse of "cpu" and "torch", so only opaque splats' outer rims differ.
"""

from __future__ import annotations

import functools
import weakref

import torch

from atgs.render.constants import NEAR
from atgs.render.types import RasterOutput


@functools.lru_cache(maxsize=1)
def gsplat_import_error() -> str | None:
    """Why gsplat cannot rasterize here, in a few words (None: it can).

    gsplat from PyPI compiles its CUDA kernels when they are first loaded (here, once per
    process; the build itself is cached by torch, a minute on 16 cores the first time). Without
    a CUDA toolkit it imports but leaves its kernels out, and every call fails later with
    ``'NoneType' object has no attribute ...``; a failed build raises. Both are reported here."""
    try:
        import gsplat  # noqa: F401
        from gsplat.cuda._backend import _C
    except Exception as e:  # ImportError, or a failed kernel build raising anything
        return f"{type(e).__name__}: {e}".splitlines()[0]
    if _C is None:
        return "gsplat found no CUDA compiler (nvcc) to build its kernels"
    return None


def forward_grad_to_view(base: torch.Tensor, view: torch.Tensor) -> None:
    """Make ``view.grad`` (``view = base[0]``) hold the gradient that reaches ``base``.

    gsplat consumes its own (1, N, 2) ``means2d``, so a gradient never reaches our (N, 2) view;
    a hook on ``base`` copies it over, so ``out.means2d.grad`` works as on the CPU backends. The
    hook holds the view weakly: a strong reference closes a cycle (base -> hook -> view -> base)
    through autograd's C++ side, which Python's collector cannot see, and every training step's
    whole rendering graph stayed alive (~20 MB a step on the built-in scene: 28 GB after 1,400
    CUDA steps)."""
    ref = weakref.ref(view)

    def copy_grad(g: torch.Tensor) -> None:
        target = ref()
        if target is not None:
            target.grad = g[0].detach()

    base.register_hook(copy_grad)


def gsplat_available() -> bool:
    """True when CUDA is present and gsplat imports."""
    return torch.cuda.is_available() and gsplat_import_error() is None


def rasterize_cuda(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    background: torch.Tensor,
    width: int,
    height: int,
    near: float = NEAR,
) -> RasterOutput:
    """gsplat rendering with our output contract (tests/test_render_cuda.py, on a GPU)."""
    if not gsplat_available():
        raise RuntimeError("rasterize(backend='cuda') needs a CUDA device and `pip install gsplat`")
    if means.device.type != "cuda":
        raise RuntimeError(f"rasterize(backend='cuda') needs CUDA tensors, got {means.device}; call .cuda()")
    from gsplat import rasterization

    n = means.shape[0]
    z = (means @ viewmat[:3, :3].T + viewmat[:3, 3])[:, 2:3]
    # Render RGB + view z and z^2 as extra channels so the depths are alpha-weighted like the CPU
    # backends.
    feats = torch.cat([colors, z, z * z], dim=-1).float()
    bg = torch.cat([background, background.new_zeros(2)]).float()
    render, alpha, meta = rasterization(
        means.float(), quats.float(), scales.float(), opacities.float(), feats,
        viewmat.float()[None], K.float()[None], width, height,
        near_plane=float(near), backgrounds=bg[None], packed=False, absgrad=False,
    )  # fmt: skip
    base = meta["means2d"]  # (1, N, 2), an autograd node inside gsplat
    radii = meta["radii"].reshape(n, -1)
    radii = radii.max(dim=-1).values if radii.shape[-1] > 1 else radii[:, 0]
    means2d = base[0]
    if base.requires_grad:
        forward_grad_to_view(base, means2d)
    return RasterOutput(
        image=render[0, :, :, :3],
        alpha=alpha[0, :, :, 0],
        depth=render[0, :, :, 3],
        depth_sq=render[0, :, :, 4],
        means2d=means2d,
        radii=radii.to(torch.int32),
        backend="cuda",
    )
