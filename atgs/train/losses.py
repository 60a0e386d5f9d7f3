"""Training losses: (1 - l) L1 + l (1 - SSIM) + lambda_v volume regulariser (+ the optional
offset regulariser, depth distortion, depth smoothness and free-space opacity, not in the paper).

SSIM is :func:`atgs.eval.metrics.ssim` (11x11 Gaussian window, 'same' padding as 3DGS), so
training and evaluation share one implementation and one Gaussian-window helper. Which of them a
step adds, with which weight, is :mod:`atgs.train.loss_terms`'s list.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, get_args

import torch

from atgs.eval.metrics import psnr as _psnr
from atgs.eval.metrics import ssim
from atgs.model.anchors import STATIC
from atgs.train.config import VolumeReduction

if TYPE_CHECKING:
    from atgs.cameras import Camera
    from atgs.geometry.free_space import FreeSpace
    from atgs.gaussians import Gaussians
    from atgs.geometry.ray_free_space import MeasuredDepths

VOLUME_REDUCTIONS = get_args(VolumeReduction)


def volume_loss(scales: torch.Tensor, reduction: str = "sum", voxel: float = 1.0) -> torch.Tensor:
    """sum (paper) or mean (authors' code) of prod(s) over the Gaussians, or ("mean-voxel") the
    mean of prod(s / voxel): the first two are in world units cubed, so their weight depends on
    the scene's scale (and "sum" on the number of Gaussians); the last is the same for a scene in
    millimetres or kilometres."""
    if reduction not in VOLUME_REDUCTIONS:
        raise ValueError(f"volume reduction must be one of {VOLUME_REDUCTIONS}, got {reduction!r}")
    if scales.numel() == 0:
        return scales.sum()
    if reduction == "mean-voxel":
        return (scales / voxel).prod(dim=1).mean()
    v = scales.prod(dim=1)
    return v.sum() if reduction == "sum" else v.mean()


def offset_loss(offsets: torch.Tensor, voxel: float, free: float = 1.0) -> torch.Tensor:
    """Mean of relu(|offset| / voxel - free)^2 over the Gaussians: offsets (N, 3) from each
    Gaussian's anchor, free within ``free`` voxels of it (a neighbouring anchor covers what lies
    further away)."""
    if offsets.numel() == 0:
        return offsets.sum()
    return torch.relu(offsets.norm(dim=1) / voxel - free).square().mean()


def depth_distortion(alpha: torch.Tensor, depth: torch.Tensor, depth_sq: torch.Tensor,
                     unit: float = 1.0, min_alpha: float = 0.01) -> torch.Tensor:
    """Mean over pixels of alpha * log(1 + var / unit^2), var the variance of the depth along the ray.

    From the rasterizer's alpha = W = sum w_i, depth = sum w_i z_i and depth_sq = sum w_i z_i^2 the
    variance is depth_sq / W - (depth / W)^2 = sum_ij w_i w_j (z_i - z_j)^2 / (2 W^2) (Mip-NeRF
    360's distortion with squared distances, normalised by W^2). It is small when a ray's weight
    sits at one depth (a thin surface) and large for a slab of semi-transparent Gaussians, which
    fits the training views but shows another picture from a new one.
    - The normalisation keeps the loss from rewarding transparency (W^2 var falls with W).
    - The logarithm makes it robust: a pixel on an object's edge blends two surfaces metres
      apart, whose variance (thousands of squared voxels) would otherwise outweigh every slab a
      few voxels thick and erase the edges (the plain variance, weight 1e-3: 12.9 dB held out
      after 700 steps of the built-in scene against 23.4 dB without).
    - alpha, taken as a constant, leaves out pixels that are mostly background, as does
      ``min_alpha``."""
    if alpha.numel() == 0:
        return alpha.sum()
    covered = alpha > min_alpha
    w = torch.where(covered, alpha, torch.ones_like(alpha))
    mean = depth / w
    var = torch.where(covered, depth_sq / w - mean * mean, torch.zeros_like(alpha)).clamp_min(0)
    return (alpha.detach() * torch.log1p(var / (unit * unit))).mean()


def depth_smoothness(alpha: torch.Tensor, depth: torch.Tensor, image: torch.Tensor, edge: float = 10.0,
                     min_alpha: float = 0.5) -> torch.Tensor:
    """Edge-aware second-order smoothness of the rendered inverse depth (H, W maps; ``image``
    (H, W, 3) the training image): the mean over pixels of ``|d[x-1] - 2 d[x] + d[x+1]|`` along
    rows plus the same along columns, ``d`` the inverse of the expected depth ``depth / alpha``
    divided by its mean over the covered pixels, each term weighted by ``exp(-edge * g)``, ``g``
    the image's absolute colour change (mean over channels) over the two pixel pairs it spans.

    A surface seen by one training camera has its colour but no depth; this prior puts it where
    its neighbours' depth continues. The inverse depth of a plane is affine in the pixel
    coordinates of a pinhole camera, so the loss is zero on any plane, a floor seen at a grazing
    angle included (a first-order prior would flatten such a floor towards the camera's depth);
    the image weight lets depth break where the colour does (an object's outline). The
    normalisation makes it free of the scene's units. Pixels covered less than ``min_alpha`` (the
    background) are left out."""
    covered = (alpha > min_alpha).to(depth.dtype)
    inv = alpha / depth.clamp_min(1e-6)
    count = covered.sum()
    inv = inv / ((inv * covered).sum() / count.clamp_min(1)).detach().clamp_min(1e-6)
    gx = (image[:, 1:] - image[:, :-1]).abs().mean(-1)
    gy = (image[1:] - image[:-1]).abs().mean(-1)
    mx = covered[:, 2:] * covered[:, 1:-1] * covered[:, :-2]
    my = covered[2:] * covered[1:-1] * covered[:-2]
    ex = torch.exp(-edge * (gx[:, 1:] + gx[:, :-1]))
    ey = torch.exp(-edge * (gy[1:] + gy[:-1]))
    lx = ((inv[:, 2:] - 2 * inv[:, 1:-1] + inv[:, :-2]).abs() * ex * mx).sum() / mx.sum().clamp_min(1)
    ly = ((inv[2:] - 2 * inv[1:-1] + inv[:-2]).abs() * ey * my).sum() / my.sum().clamp_min(1)
    return lx + ly


def free_space_loss(opacities: torch.Tensor, means: torch.Tensor, free: "FreeSpace") -> torch.Tensor:
    """Mean over the Gaussians of the opacity of those standing in space the measured points prove
    empty (atgs.geometry.free_space): pushes them transparent, and pruning then removes them. A Gaussian
    there explains some training camera's pixels with something another camera sees through; a
    held-out camera sees it as a floater. Only the opacity is pushed (the test is on detached
    means): moving a Gaussian out of empty space is the image loss's job."""
    if opacities.numel() == 0:
        return opacities.sum()
    empty, _ = free.test(means.detach())
    return (opacities * empty.to(opacities.dtype)).mean()


def per_keyframe_gaussians(anchor_keyframe: torch.Tensor, anchor_ids: torch.Tensor) -> torch.Tensor:
    """(N,) bool: which decoded Gaussians (by their anchor, ``anchor_ids``) belong to per-keyframe
    anchors rather than always-active ones: the ``moving`` of :func:`ray_free_space_loss`."""
    return anchor_keyframe.index_select(0, anchor_ids) != STATIC


def ray_free_space_loss(gaussians: "Gaussians", moving: torch.Tensor, measured: "MeasuredDepths", slot: int,
                        frame: int, camera: "Camera", backend: str = "auto", **render) -> torch.Tensor | None:
    """The opacity that training camera ``slot``'s rays accumulate in front of their measured
    depth (atgs.geometry.ray_free_space), per pixel of its image at ``frame``, averaged over the image.

    The Gaussians standing in front of the measured depth of the ray through their centre
    (``moving``: (N,) bool, those of per-keyframe anchors, judged only at measured frames) are
    rendered alone; a pixel counts where the depth they accumulate lies in front of that pixel's
    measured depth, so a Gaussian straddling a depth edge is charged only on the rays it
    occludes. Gradients reach the opacities, scales, rotations and means of those Gaussians.
    None when no Gaussian stands in front of a measured depth. ``render``: further keywords of
    :func:`atgs.render.rasterize` (the near plane)."""
    from atgs.cameras import to_camera_frame
    from atgs.render import rasterize

    means = gaussians.means.detach()
    limit = measured.limits(slot, frame, means, moving)
    z = to_camera_frame(camera, means)[:, 2]
    front = torch.isfinite(limit) & (z < measured.margin * limit)
    idx = front.nonzero().squeeze(1)
    if idx.numel() == 0:
        return None
    g = gaussians.map(lambda x: x.index_select(0, idx))
    out = rasterize(g.means, g.quats, g.scales, g.opacities, torch.zeros_like(g.colors), camera.w2c, camera.K,
                    camera.width, camera.height, backend=backend, **render)
    alpha = out.alpha
    depth_px = measured.pixel_depths(slot, frame).to(alpha.dtype)
    with torch.no_grad():  # in front of the pixel's measured depth (unmeasured pixels: never)
        covered = alpha > 0
        mean_depth = out.depth / alpha.clamp_min(1e-12)
        charged = covered & torch.isfinite(depth_px) & (mean_depth < measured.margin * depth_px)
    return (alpha * charged.to(alpha.dtype)).sum() / alpha.numel()


def image_loss(img: torch.Tensor, ref: torch.Tensor, lambda_ssim: float) -> torch.Tensor:
    l1 = (img - ref).abs().mean()
    if lambda_ssim <= 0:
        return l1
    return (1 - lambda_ssim) * l1 + lambda_ssim * (1 - ssim(img, ref))


def psnr(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """PSNR of a training view as a 0-d tensor on the images' device (the trainer reads the
    step's values back at once)."""
    return _psnr(img.detach(), ref.detach())
