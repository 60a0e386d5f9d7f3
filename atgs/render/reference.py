"""Slow, dense reference rasterization of 2D Gaussians in plain PyTorch.

Every pixel evaluates every Gaussian (sorted front to back by view depth) with the exact rules
of SPEC section 2; autograd gives the gradients, and it runs in float64 too. The only
shortcut is per pixel block: Gaussians whose 3-sigma square misses the block are dropped before
the dense evaluation (``prefilter=False`` turns that off; the result is identical because the
square contains every pixel a Gaussian can touch). Blocks are checkpointed when gradients are
needed so memory stays bounded.
"""

from __future__ import annotations

import torch
from torch.utils.checkpoint import checkpoint

from atgs.render.constants import ALPHA_MAX, ALPHA_MIN, SIGMA_CUTOFF, T_MIN


def blend_pixels(
    px: torch.Tensor,
    py: torch.Tensor,
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    depths: torch.Tensor,
    background: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Composite Gaussians (already sorted front to back) at P pixel centers (px, py).

    Returns color (P,3), alpha (P,), depth (P,) and depth_sq (P,) where depth = sum_i alpha_i T_i z_i
    (alpha-weighted, not normalized by the accumulated alpha) and depth_sq the same sum of z_i^2.
    """
    dx = means2d[None, :, 0] - px[:, None]  # (P, N)
    dy = means2d[None, :, 1] - py[:, None]
    a, b, c = conics[:, 0], conics[:, 1], conics[:, 2]
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    # Pixels beyond the 3-sigma ellipse (sigma > 4.5) or with sigma < 0 are skipped.
    inside = (sigma >= 0) & (sigma <= SIGMA_CUTOFF)
    sigma = torch.where(inside, sigma, torch.zeros_like(sigma))  # keep exp() finite
    alpha = torch.clamp(opacities[None, :] * torch.exp(-sigma), max=ALPHA_MAX)
    used = inside & (alpha >= ALPHA_MIN)
    alpha = torch.where(used, alpha, torch.zeros_like(alpha))
    # Stop rule: a Gaussian is dropped (with all later ones) once T (1 - alpha) < T_MIN.
    # The running product is non-increasing, so one comparison against it suffices.
    with torch.no_grad():
        keep = torch.cumprod(1 - alpha, dim=1) >= T_MIN
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    one_minus = 1 - alpha
    T_after = torch.cumprod(one_minus, dim=1)
    T_before = torch.cat([torch.ones_like(T_after[:, :1]), T_after[:, :-1]], dim=1)
    weights = alpha * T_before
    T_final = T_after[:, -1] if T_after.shape[1] > 0 else torch.ones_like(px)
    color = weights @ colors + T_final[:, None] * background[None, :]
    depth = weights @ depths
    depth_sq = weights @ (depths * depths)
    return color, 1 - T_final, depth, depth_sq


def rasterize_reference(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    depths: torch.Tensor,
    radii: torch.Tensor,
    width: int,
    height: int,
    background: torch.Tensor,
    block: int = 32,
    prefilter: bool = True,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Image (H,W,3), alpha (H,W), depth (H,W), depth_sq (H,W) of the projected Gaussians
    (``radii > 0`` only)."""
    dtype, device = means2d.dtype, means2d.device
    visible = torch.nonzero(radii > 0).flatten()
    order = visible[torch.argsort(depths.detach()[visible], stable=True)]
    m2, co, op, col, dep = (t[order] for t in (means2d, conics, opacities, colors, depths))
    r = radii[order].to(dtype)
    need_grad = torch.is_grad_enabled() and any(
        t.requires_grad for t in (means2d, conics, opacities, colors, depths, background)
    )
    rows = []
    for y0 in range(0, height, block):
        y1 = min(height, y0 + block)
        row = []
        for x0 in range(0, width, block):
            x1 = min(width, x0 + block)
            ys = torch.arange(y0, y1, dtype=dtype, device=device) + 0.5
            xs = torch.arange(x0, x1, dtype=dtype, device=device) + 0.5
            py, px = (g.reshape(-1) for g in torch.meshgrid(ys, xs, indexing="ij"))
            if prefilter:
                u, v = m2[:, 0].detach(), m2[:, 1].detach()
                hit = (u + r >= x0) & (u - r <= x1) & (v + r >= y0) & (v - r <= y1)
                sel = torch.nonzero(hit).flatten()
                args = (px, py, m2[sel], co[sel], op[sel], col[sel], dep[sel], background)
            else:
                args = (px, py, m2, co, op, col, dep, background)
            if need_grad:
                c, a, d, q = checkpoint(blend_pixels, *args, use_reentrant=False)
            else:
                c, a, d, q = blend_pixels(*args)
            h, w = y1 - y0, x1 - x0
            row.append((c.reshape(h, w, 3), a.reshape(h, w), d.reshape(h, w), q.reshape(h, w)))
        rows.append(tuple(torch.cat([blk[i] for blk in row], dim=1) for i in range(4)))
    image, alpha, depth, depth_sq = (torch.cat([row[i] for row in rows], dim=0) for i in range(4))
    return image, alpha, depth, depth_sq
