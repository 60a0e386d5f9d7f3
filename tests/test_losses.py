"""Training losses against analytic values and finite differences."""

import pytest
import torch

from atgs.train.losses import offset_loss, volume_loss


def test_volume_loss_is_the_sum_or_mean_of_scale_products():
    s = torch.tensor([[1.0, 2.0, 3.0], [0.5, 0.5, 4.0]])
    assert float(volume_loss(s, "sum")) == 7.0 and float(volume_loss(s, "mean")) == 3.5
    assert float(volume_loss(torch.zeros(0, 3))) == 0.0


def test_mean_voxel_volume_loss_does_not_depend_on_the_scene_units():
    s = torch.tensor([[1.0, 2.0, 3.0], [0.5, 0.5, 4.0]])
    # (1*2*3 + 0.5*0.5*4) / 2 / 0.5^3
    assert abs(float(volume_loss(s, "mean-voxel", voxel=0.5)) - 3.5 / 0.125) < 1e-5
    for k in (1e-3, 1e3):  # the same scene in other units: the same loss; "mean" changes by k^3
        assert abs(float(volume_loss(s * k, "mean-voxel", voxel=0.5 * k)) - 28.0) < 1e-3
        assert abs(float(volume_loss(s * k, "mean")) / 3.5 - k ** 3) < 1e-3 * k ** 3
    with pytest.raises(ValueError, match="volume reduction"):
        volume_loss(s, "median")


def test_offset_loss_is_free_within_the_radius_and_a_squared_hinge_beyond():
    voxel = 0.5
    off = torch.tensor([[0.3, 0.0, 0.0], [0.0, 1.5, 0.0], [0.0, 0.0, -2.0]])
    # |off| / voxel = 0.6, 3, 4 -> hinge at 1 voxel: 0, 2, 3 -> mean of squares (0 + 4 + 9) / 3
    assert abs(float(offset_loss(off, voxel, free=1.0)) - 13 / 3) < 1e-6
    assert float(offset_loss(off, voxel, free=5.0)) == 0.0
    assert float(offset_loss(torch.zeros(0, 3), voxel)) == 0.0


def test_offset_loss_gradient_matches_finite_differences():
    torch.manual_seed(0)
    off = (torch.randn(6, 3, dtype=torch.float64) * 0.8).requires_grad_(True)
    offset_loss(off, 0.3, 1.5).backward()
    eps = 1e-6
    for i in range(6):
        for j in range(3):
            d = torch.zeros_like(off)
            d[i, j] = eps
            with torch.no_grad():
                fd = (offset_loss(off + d, 0.3, 1.5) - offset_loss(off - d, 0.3, 1.5)) / (2 * eps)
            assert abs(float(fd) - float(off.grad[i, j])) < 1e-6
    # the gradient points the offsets back toward their anchors
    assert float((off.grad * off).sum()) > 0
