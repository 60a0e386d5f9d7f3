"""The "cpu" backend: C++ projection + compiled tile rasterizer, both with hand-written backward passes."""

from __future__ import annotations

import torch

from atgs.render.build import cpu_backend_error, load_extension
from atgs.render.constants import (
    ALPHA_MAX, ALPHA_MIN, CLAMP_MARGIN, DILATION, MAX_RADIUS, NEAR, QUAT_EPS, RADIUS_SIGMAS, SIGMA_CUTOFF, T_MIN,
)  # fmt: skip
from atgs.render.projection import Projected
from atgs.render.types import RasterOutput

__all__ = ["cpu_backend_error", "pair_counts", "project_cpu", "rasterize_cpu", "rasterize_2d_cpu"]

TILE = 16


def project_consts(near: float = NEAR) -> list[float]:
    """The projection kernel's constants: the near plane, then atgs.render.constants'."""
    return [float(near), DILATION, CLAMP_MARGIN, RADIUS_SIGMAS, QUAT_EPS, float(MAX_RADIUS)]


class _Project(torch.autograd.Function):
    """(means, quats, scales) -> (means2d, conics, depths, radii); camera is constant."""

    @staticmethod
    def forward(ctx, means, quats, scales, viewmat, K, width, height, near):  # type: ignore[override]
        threads = torch.get_num_threads()
        means2d, conics, depths, radii = load_extension().project_forward(
            means, quats, scales, viewmat, K, width, height, threads, project_consts(near)
        )
        ctx.save_for_backward(means, quats, scales, viewmat, K)
        ctx.size = (width, height, threads, near)
        ctx.mark_non_differentiable(radii)
        return means2d, conics, depths, radii

    @staticmethod
    def backward(ctx, v_means2d, v_conics, v_depths, _v_radii):  # type: ignore[override]
        means, quats, scales, viewmat, K = ctx.saved_tensors
        width, height, threads, near = ctx.size
        g_means, g_quats, g_scales = load_extension().project_backward(
            means, quats, scales, viewmat, K, width, height, threads, project_consts(near),
            v_means2d.contiguous(), v_conics.contiguous(), v_depths.contiguous(),
        )  # fmt: skip
        return g_means, g_quats, g_scales, None, None, None, None, None


def project_cpu(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    near: float = NEAR,
) -> Projected:
    """C++ twin of :func:`atgs.render.projection.project` (float32, no camera gradients)."""
    m2, con, dep, rad = _Project.apply(
        means.float().contiguous(), quats.float().contiguous(), scales.float().contiguous(),
        viewmat.detach().float().contiguous(), K.detach().float().contiguous(), width, height, float(near),
    )  # fmt: skip
    return Projected(means2d=m2, conics=con, depths=dep, radii=rad)


class _Rasterize2D(torch.autograd.Function):
    """(means2d, conics, opacities, colors, depths, background) -> (image, alpha, depth, depth_sq)."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, depths, background, radii, width, height):  # type: ignore[override]
        threads = torch.get_num_threads()
        image, alpha, depth, depth_sq, t_final, last, offsets, ids, slots, order, first, _stats = load_extension().forward(
            means2d, conics, opacities, colors, depths, radii, background,
            width, height, TILE, threads, ALPHA_MAX, ALPHA_MIN, T_MIN, SIGMA_CUTOFF,
        )  # fmt: skip
        ctx.save_for_backward(
            means2d, conics, opacities, colors, depths, radii, background, t_final, last, offsets, ids, slots, order, first
        )
        ctx.size = (width, height, threads)
        return image, alpha, depth, depth_sq

    @staticmethod
    def backward(ctx, grad_image, grad_alpha, grad_depth, grad_depth_sq):  # type: ignore[override]
        saved = ctx.saved_tensors
        width, height, threads = ctx.size
        grads = load_extension().backward(
            *saved, grad_image, grad_alpha, grad_depth, grad_depth_sq,
            width, height, TILE, threads, ALPHA_MAX, ALPHA_MIN, T_MIN, SIGMA_CUTOFF,
        )  # fmt: skip
        return (*grads, None, None, None)


def rasterize_2d_cpu(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    depths: torch.Tensor,
    background: torch.Tensor,
    radii: torch.Tensor,
    width: int,
    height: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Composite projected Gaussians front to back (sorted by ``depths``): image, alpha, depth,
    depth_sq."""
    return _Rasterize2D.apply(
        means2d.contiguous(), conics.contiguous(), opacities.contiguous(), colors.contiguous(),
        depths.contiguous(), background.contiguous(), radii.to(torch.int32).contiguous(), width, height,
    )  # fmt: skip


def rasterize_cpu(
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
    """Float32 rendering on the CPU; float64 inputs are cast (their gradients come back float64)."""
    if viewmat.requires_grad or K.requires_grad:
        raise ValueError(
            "rasterize(backend='cpu') does not differentiate the camera; "
            "detach viewmat/K or use backend='torch'"
        )
    f32 = [t.float() for t in (means, quats, scales, opacities, colors, viewmat, K, background)]
    means, quats, scales, opacities, colors, viewmat, K, background = f32
    proj = project_cpu(means, quats, scales, viewmat, K, width, height, near)
    image, alpha, depth, depth_sq = rasterize_2d_cpu(
        proj.means2d, proj.conics, opacities, colors, proj.depths, background, proj.radii, width, height
    )
    return RasterOutput(image, alpha, depth, depth_sq, proj.means2d, proj.radii, backend="cpu")


@torch.no_grad()
def pair_counts(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
) -> dict[str, int]:
    """Work statistics of one render (for benchmarks): pixel-Gaussian pairs actually composited
    and (tile, Gaussian) list entries."""
    proj = project_cpu(means, quats, scales, viewmat, K, width, height)
    stats = load_extension().forward(
        proj.means2d.contiguous(), proj.conics.contiguous(), opacities.float().contiguous(),
        torch.zeros_like(means).float(), proj.depths.contiguous(), proj.radii, torch.zeros(3), width, height,
        TILE, torch.get_num_threads(), ALPHA_MAX, ALPHA_MIN, T_MIN, SIGMA_CUTOFF,
    )[-1]  # fmt: skip
    return {"blended_pairs": int(stats[0]), "tile_pairs": int(stats[1]), "visible": int((proj.radii > 0).sum())}
