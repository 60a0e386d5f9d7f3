"""Training losses: (1 - l) L1 + l (1 - SSIM) + lambda_v volume regulariser.

SSIM is :func:`atgs.eval.metrics.ssim` (11x11 Gaussian window, 'same' padding as 3DGS), so
training and evaluation share one implementation and one Gaussian-window helper.
"""

from __future__ import annotations

import torch

from atgs.eval.metrics import psnr as _psnr
from atgs.eval.metrics import ssim


def volume_loss(scales: torch.Tensor, reduction: str = "sum") -> torch.Tensor:
    """sum (paper) or mean (authors' code) of prod(s) over the Gaussians."""
    if scales.numel() == 0:
        return scales.sum()
    v = scales.prod(dim=1)
    return v.sum() if reduction == "sum" else v.mean()


def image_loss(img: torch.Tensor, ref: torch.Tensor, lambda_ssim: float) -> torch.Tensor:
    l1 = (img - ref).abs().mean()
    if lambda_ssim <= 0:
        return l1
    return (1 - lambda_ssim) * l1 + lambda_ssim * (1 - ssim(img, ref))


def psnr(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """PSNR of a training view as a 0-d tensor on the images' device (the trainer reads the
    step's values back at once)."""
    return _psnr(img.detach(), ref.detach())
