"""3D smoothing filter (Mip-Splatting's, Yu et al. CVPR 2024; not in the ATGS paper).

A Gaussian can only be resolved as finely as the training cameras sample it: nothing in training
constrains detail finer than one training pixel, so Gaussians shrink into needles and flat disks
that look right from the training views and alias or smear from any view that samples the
place more finely (a held-out camera closer to the floor than its neighbours). The filter
convolves every Gaussian with an isotropic Gaussian of variance ``s2 / nu^2``, ``nu`` the
highest sampling rate (focal length / depth, pixels per world unit) at which a training camera
sees the Gaussian's anchor, ``s2`` the filter's size in squared training pixels:
``Sigma' = Sigma + (s2 / nu^2) I``; the opacity is scaled by ``sqrt(det Sigma / det Sigma')`` so that
the Gaussian's integral is kept. An isotropic term commutes with the rotation, so the filtered
scales are ``sqrt(scale^2 + s2 / nu^2)`` per axis. Anchors no training camera sees are not filtered.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from atgs.cameras import Camera, pinhole_pixels, to_camera_frame

# An anchor counts as seen by a camera inside its image grown by this fraction per side (the
# decode's frustum margin): Gaussians reach a little beyond their anchor.
VIEW_MARGIN = 0.15


def sampling_rates(mu: torch.Tensor, cameras: Sequence[Camera], near: float = 0.01) -> torch.Tensor:
    """(A,) highest focal / depth over ``cameras`` that see each anchor position (0: none does)."""
    best = torch.zeros(mu.shape[0], dtype=torch.float32, device=mu.device)
    for cam in cameras:
        pc = to_camera_frame(cam, mu.float())
        z = pc[:, 2]
        zs = z.clamp_min(near)
        u, v = pinhole_pixels(cam, pc, zs)
        mw, mh = VIEW_MARGIN * cam.width, VIEW_MARGIN * cam.height
        seen = (z > near) & (u > -mw) & (u < cam.width + mw) & (v > -mh) & (v < cam.height + mh)
        rate = max(float(cam.fx), float(cam.fy)) / zs
        best = torch.where(seen, torch.maximum(best, rate), best)
    return best


def filter_variance(rates: torch.Tensor, size: float) -> torch.Tensor:
    """(A,) world-space variance of the filter: ``size / rate^2``, 0 where no camera sees."""
    seen = rates > 0
    return torch.where(seen, size / torch.where(seen, rates, torch.ones_like(rates)) ** 2, torch.zeros_like(rates))


def smooth(scales: torch.Tensor, opacities: torch.Tensor, variance: torch.Tensor
           ) -> tuple[torch.Tensor, torch.Tensor]:
    """Filtered (scales (A, q, 3), opacities (A, q)) of Gaussians (scales > 0) whose anchors have
    filter ``variance`` (A,). A Gaussian flat along an axis gets the filter's width there and its
    opacity scaled by its thinness; gradients stay finite at zero scales (no square root of 0
    where the variance is positive, and no filter where it is 0)."""
    var = variance[:, None, None]
    on = var > 0
    width = torch.sqrt(scales * scales + torch.where(on, var, torch.ones_like(var)))
    ratio = torch.where(on, scales / width, torch.ones_like(scales))  # = sqrt(s^2 / (s^2 + var))
    return torch.where(on, width, scales), opacities * ratio.prod(dim=-1)
