"""The "cpu" backend: torch projection + compiled tile rasterizer with a hand-written backward."""

from __future__ import annotations

import torch

from atgs.render.build import cpu_backend_error, load_extension
from atgs.render.constants import (
    ALPHA_MAX, ALPHA_MIN, CLAMP_MARGIN, DILATION, MAX_RADIUS, NEAR, QUAT_EPS, RADIUS_SIGMAS, SIGMA_CUTOFF, T_MIN,
)  # fmt: skip
from atgs.render.projection import Projected
from atgs.render.types import RasterOutput

__all__ = ["cpu_backend_error", "project_cpu", "rasterize_cpu", "rasterize_2d_cpu"]

TILE = 16
PROJECT_CONSTS = [NEAR, DILATION, CLAMP_MARGIN, RADIUS_SIGMAS, QUAT_EPS, float(MAX_RADIUS)]


class _Project(torch.autograd.Function):
    """(means, quats, scales) -> (means2d, conics, depths, radii); camera is constant."""

    @staticmethod
    def forward(ctx, means, quats, scales, viewmat, K, width, height):  # type: ignore[override]
        threads = torch.get_num_threads()
        means2d, conics, depths, radii = load_extension().project_forward(
            means, quats, scales, viewmat, K, width, height, threads, PROJECT_CONSTS
        )
        ctx.save_for_backward(means, quats, scales, viewmat, K)
        ctx.size = (width, height, threads)
        ctx.mark_non_differentiable(radii)
        return means2d, conics, depths, radii

    @staticmethod
    def backward(ctx, v_means2d, v_conics, v_depths, _v_radii):  # type: ignore[override]
        means, quats, scales, viewmat, K = ctx.saved_tensors
        width, height, threads = ctx.size
        g_means, g_quats, g_scales = load_extension().project_backward(
            means, quats, scales, viewmat, K, width, height, threads, PROJECT_CONSTS,
            v_means2d.contiguous(), v_conics.contiguous(), v_depths.contiguous(),
        )  # fmt: skip
        return g_means, g_quats, g_scales, None, None, None, None


def project_cpu(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
) -> Projected:
    """C++ twin of :func:`atgs.render.projection.project` (float32, no camera gradients)."""
    m2, con, dep, rad = _Project.apply(
        means.float().contiguous(), quats.float().contiguous(), scales.float().contiguous(),
        viewmat.detach().float().contiguous(), K.detach().float().contiguous(), width, height,
    )  # fmt: skip
    return Projected(means2d=m2, conics=con, depths=dep, radii=rad)


class _Rasterize2D(torch.autograd.Function):
    """(means2d, conics, opacities, feats, background) -> (out (H,W,C), alpha (H,W))."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, feats, background, radii, width, height):  # type: ignore[override]
        ext = load_extension()
        threads = torch.get_num_threads()
        depth_key = feats[:, -1].contiguous()  # sort key: view depth (last feature channel)
        out, t_final, last, offsets, ids = ext.forward(
            means2d, conics, opacities, feats, depth_key, radii, background,
            width, height, TILE, threads, ALPHA_MAX, ALPHA_MIN, T_MIN, SIGMA_CUTOFF,
        )  # fmt: skip
        ctx.save_for_backward(means2d, conics, opacities, feats, radii, background, t_final, last, offsets, ids)
        ctx.size = (width, height, threads)
        ctx.mark_non_differentiable(t_final)
        return out, 1 - t_final

    @staticmethod
    def backward(ctx, grad_out, grad_alpha):  # type: ignore[override]
        means2d, conics, opacities, feats, radii, background, t_final, last, offsets, ids = ctx.saved_tensors
        width, height, threads = ctx.size
        ext = load_extension()
        g_m2, g_con, g_op, g_ft, g_bg = ext.backward(
            means2d, conics, opacities, feats, radii, background, t_final, last, offsets, ids,
            grad_out.contiguous(), grad_alpha.contiguous(),
            width, height, TILE, threads, ALPHA_MAX, ALPHA_MIN, T_MIN, SIGMA_CUTOFF,
        )  # fmt: skip
        return g_m2, g_con, g_op, g_ft, g_bg, None, None, None


def rasterize_2d_cpu(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    feats: torch.Tensor,
    background: torch.Tensor,
    radii: torch.Tensor,
    width: int,
    height: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite projected Gaussians; ``feats`` (N,C<=4) must end with the view depth (sort key)."""
    return _Rasterize2D.apply(
        means2d.contiguous(), conics.contiguous(), opacities.contiguous(), feats.contiguous(),
        background.contiguous(), radii.to(torch.int32).contiguous(), width, height,
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
) -> RasterOutput:
    """Float32 rendering on the CPU; float64 inputs are cast (their gradients come back float64)."""
    if viewmat.requires_grad or K.requires_grad:
        raise ValueError(
            "rasterize(backend='cpu') does not differentiate the camera; "
            "detach viewmat/K or use backend='torch'"
        )
    f32 = [t.float() for t in (means, quats, scales, opacities, colors, viewmat, K, background)]
    means, quats, scales, opacities, colors, viewmat, K, background = f32
    proj = project_cpu(means, quats, scales, viewmat, K, width, height)
    feats = torch.cat([colors, proj.depths[:, None]], dim=1)
    bg4 = torch.cat([background, background.new_zeros(1)])
    out, alpha = rasterize_2d_cpu(proj.means2d, proj.conics, opacities, feats, bg4, proj.radii, width, height)
    return RasterOutput(out[..., :3], alpha, out[..., 3], proj.means2d, proj.radii, backend="cpu")
