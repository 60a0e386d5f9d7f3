"""Training losses against analytic values and finite differences."""

import math

import pytest
import torch

from atgs.train.losses import depth_distortion, offset_loss, volume_loss


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


def _ray_sums(w: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """alpha, depth and depth_sq of rays with blending weights w (P, N) at depths z (P, N)."""
    return w.sum(1), (w * z).sum(1), (w * z * z).sum(1)


def test_depth_distortion_equals_the_pairwise_spread_of_each_ray():
    """Against the pairwise form sum_ij w_i w_j (z_i - z_j)^2 / (2 W^2), one pixel at a time."""
    g = torch.Generator().manual_seed(0)
    w = torch.rand(40, 6, generator=g, dtype=torch.float64) / 6
    w[:5] *= 0.01  # rays that are mostly background: left out
    z = 2 + 10 * torch.rand(40, 6, generator=g, dtype=torch.float64)
    unit = 0.3
    expect = []
    for p in range(40):
        W = float(w[p].sum())
        if W <= 0.01:
            expect.append(0.0)
            continue
        var = sum(float(w[p, i] * w[p, j] * (z[p, i] - z[p, j]) ** 2) for i in range(6) for j in range(6)) / (2 * W * W)
        expect.append(W * math.log1p(var / unit ** 2))
    got = depth_distortion(*_ray_sums(w, z), unit=unit)
    assert abs(float(got) - sum(expect) / 40) < 1e-9
    assert sum(e == 0.0 for e in expect) == 5


def test_depth_distortion_is_zero_on_thin_surfaces_and_grows_with_the_spread():
    w = torch.full((3, 4), 0.2, dtype=torch.float64)
    z = torch.tensor([[5.0] * 4, [4.9, 5.0, 5.0, 5.1], [4.0, 5.0, 5.0, 6.0]], dtype=torch.float64)
    per_ray = [float(depth_distortion(*_ray_sums(w[i:i + 1], z[i:i + 1]), unit=0.1)) for i in range(3)]
    assert per_ray[0] < 1e-9 < per_ray[1] < per_ray[2]


def test_depth_distortion_does_not_reward_transparency():
    """Scaling every weight of a ray leaves the loss's gradient flat: only the spread counts (the
    unnormalised alpha * depth_sq - depth^2 falls with the square of the scale)."""
    g = torch.Generator().manual_seed(1)
    w0 = torch.rand(20, 5, generator=g, dtype=torch.float64) / 5
    z = 3 + 5 * torch.rand(20, 5, generator=g, dtype=torch.float64)
    c = torch.tensor(0.8, dtype=torch.float64, requires_grad=True)
    depth_distortion(*_ray_sums(c * w0, z), unit=0.5).backward()
    assert abs(float(c.grad)) < 1e-9
    zz = z.clone().requires_grad_(True)  # ... while moving the depths together lowers it
    depth_distortion(*_ray_sums(w0, zz), unit=0.5).backward()
    step = zz - 1e-3 * zz.grad
    assert float(depth_distortion(*_ray_sums(w0, step), unit=0.5)) < float(depth_distortion(*_ray_sums(w0, z), unit=0.5))
    spread = lambda t: float((t - (w0 * t).sum(1, keepdim=True) / w0.sum(1, keepdim=True)).abs().max())  # noqa: E731
    assert spread(step.detach()) < spread(z)


def test_depth_distortion_of_a_render_matches_its_gaussians():
    """Through the rasterizer: two Gaussians covering the image centre at depths 4 and 6 give the
    variance of their two depths under their blending weights (analytic for a two-point ray)."""
    from atgs.render import rasterize

    K = torch.tensor([[50.0, 0, 16], [0, 50.0, 16], [0, 0, 1]], dtype=torch.float64)
    means = torch.tensor([[0.0, 0, 4], [0.0, 0, 6]], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=torch.float64)
    scales = torch.tensor([[1.0, 1, 0.01], [1.5, 1.5, 0.01]], dtype=torch.float64)
    op = torch.tensor([0.6, 0.9], dtype=torch.float64)
    for backend in ("torch", "cpu"):
        out = rasterize(means, quats, scales, op, torch.zeros(2, 3, dtype=torch.float64), torch.eye(4, dtype=torch.float64),
                        K, 32, 32, backend=backend)
        y = x = 16  # pixel centre (16.5, 16.5): both Gaussians nearly at their peak
        a1 = 0.6 * math.exp(-0.5 * (0.5 ** 2 * 2) / (50 * 1.0 / 4) ** 2)  # screen sigma = f * s / z
        a2 = 0.9 * math.exp(-0.5 * (0.5 ** 2 * 2) / (50 * 1.5 / 6) ** 2)
        w1, w2 = a1, a2 * (1 - a1)
        var = w1 * w2 * (6 - 4) ** 2 / (w1 + w2) ** 2
        px = [t[y:y + 1, x:x + 1].reshape(1) for t in (out.alpha, out.depth, out.depth_sq)]
        got = float(depth_distortion(*px, unit=1.0)) / float(px[0])
        assert abs(got - math.log1p(var)) < 2e-3, backend


def test_the_trainer_loss_is_the_weighted_sum_of_the_active_terms(tmp_path):
    """atgs.train.loss_terms: a weight of 0 leaves its term out; the others are weighted and
    summed in their order."""
    from atgs.render import rasterize_gaussians
    from atgs.train.config import preset
    from atgs.train.losses import image_loss
    from atgs.train.trainer import Trainer
    from builders import make_toy_scene

    scene = make_toy_scene(num_frames=4, num_cameras=4, width=32, height=24, keyframes=2)
    m, t = preset("tiny")
    t.lambda_volume, t.lambda_distortion = 0.0, 0.3
    tr = Trainer(scene, m, t, tmp_path)
    ci = tr.train_idx[0]
    cam, gt = tr.cams[ci], tr.images.get(ci, 0)
    with torch.no_grad():
        dec = tr.model.decode_frame(0, [cam], track=False)
        out = rasterize_gaussians(dec.gaussians, cam)
        terms = tr.loss_terms(dec, out, gt)
        total = tr.compute_loss(dec, out, gt)
    assert list(terms) == ["image", "offset", "distortion", "depth_smooth"], "volume (0) and free space (0) are off"
    assert float(terms["image"]) == pytest.approx(float(image_loss(out.image, gt, t.lambda_ssim)))
    assert float(terms["distortion"]) == pytest.approx(
        0.3 * float(depth_distortion(out.alpha, out.depth, out.depth_sq, tr.model.voxel_size)))
    assert float(total) == pytest.approx(sum(float(v) for v in terms.values()))
