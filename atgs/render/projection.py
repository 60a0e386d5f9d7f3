"""EWA projection of 3D Gaussians to 2D screen-space Gaussians, in plain PyTorch.

This is the projection used by the ``"torch"`` reference backend; autograd differentiates it.
Conventions (SPEC section 2): OpenCV camera (x right, y down, z forward), pixel centers at
+0.5, ``Sigma2d = J W Sigma W^T J^T + 0.3 I`` with gsplat's Jacobian clamp, a near plane
(``near``, 0.01 by default), radius = ceil(3 sqrt(lambda_max)) with
``lambda_max = mid + sqrt(max(0.1, mid^2 - det))``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from atgs.render.constants import CLAMP_MARGIN, DILATION, MAX_RADIUS, NEAR, QUAT_EPS, RADIUS_SIGMAS


@dataclass
class Projected:
    """Per-Gaussian screen-space quantities (N rows; culled Gaussians have ``radii == 0``)."""

    means2d: torch.Tensor  # (N, 2) pixel coordinates
    conics: torch.Tensor  # (N, 3) inverse 2D covariance (a, b, c): [[a, b], [b, c]]
    depths: torch.Tensor  # (N,) view-space z
    radii: torch.Tensor  # (N,) int32, 0 = culled


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """(N,4) quaternions (w,x,y,z), any norm -> (N,3,3) rotation matrices.

    Normalized as q / max(|q|, QUAT_EPS): a zero quaternion gives the identity, never NaN.
    """
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(QUAT_EPS)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(-1, 3, 3)


def clamp_limits(K: torch.Tensor, width: int, height: int) -> tuple[torch.Tensor, ...]:
    """gsplat's Jacobian clamp: x/z in [-lim_x_neg, lim_x_pos], y/z in [-lim_y_neg, lim_y_pos]."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    return (
        cx / fx + CLAMP_MARGIN * tan_x,
        (width - cx) / fx + CLAMP_MARGIN * tan_x,
        cy / fy + CLAMP_MARGIN * tan_y,
        (height - cy) / fy + CLAMP_MARGIN * tan_y,
    )


def project(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    near: float = NEAR,
) -> Projected:
    """Project N Gaussians; differentiable w.r.t. every tensor input (including the camera).
    Those at view-space z <= ``near`` are culled."""
    Rv, tv = viewmat[:3, :3], viewmat[:3, 3]
    p = means @ Rv.T + tv
    x, y, z = p.unbind(-1)
    in_front = z > near
    zs = torch.where(in_front, z, torch.ones_like(z))  # safe divisor for culled Gaussians
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]

    # Jacobian of the perspective projection at the (clamped) mean; clamping x/z gates the
    # gradient exactly like gsplat does (torch.clamp passes no gradient outside the bounds).
    lxn, lxp, lyn, lyp = clamp_limits(K, width, height)
    tx = zs * torch.minimum(torch.maximum(x / zs, -lxn), lxp)
    ty = zs * torch.minimum(torch.maximum(y / zs, -lyn), lyp)
    zero = torch.zeros_like(zs)
    J = torch.stack(
        [fx / zs, zero, -fx * tx / (zs * zs), zero, fy / zs, -fy * ty / (zs * zs)], dim=-1
    ).reshape(-1, 2, 3)

    # Sigma2d = (J Rv R S)(J Rv R S)^T + 0.3 I; its determinant via Lagrange's identity
    # |r1|^2 |r2|^2 - (r1.r2)^2 = |r1 x r2|^2 stays >= 0 even for huge, flat splats.
    M = quat_to_rotmat(quats) * scales[:, None, :]
    TM = J @ Rv @ M  # (N, 2, 3)
    r1, r2 = TM[:, 0], TM[:, 1]
    a0, b, c0 = (r1 * r1).sum(-1), (r1 * r2).sum(-1), (r2 * r2).sum(-1)
    cross = torch.linalg.cross(r1, r2)
    a, c = a0 + DILATION, c0 + DILATION
    det = (cross * cross).sum(-1) + DILATION * (a0 + c0) + DILATION * DILATION
    conics = torch.stack([c / det, -b / det, a / det], dim=-1)

    means2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], dim=-1)

    with torch.no_grad():
        mid = 0.5 * (a + c)
        lam = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
        r = torch.ceil(RADIUS_SIGMAS * torch.sqrt(lam)).clamp(max=MAX_RADIUS)
        u, v = means2d.unbind(-1)
        visible = in_front & (u + r > 0) & (u - r < width) & (v + r > 0) & (v - r < height)
        visible &= torch.isfinite(r) & torch.isfinite(conics).all(-1) & (det > 0)
        radii = torch.where(visible, r, torch.zeros_like(r)).to(torch.int32)
    return Projected(means2d=means2d, conics=conics, depths=z, radii=radii)
