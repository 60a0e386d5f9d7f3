"""atgs.train.losses.depth_smoothness against analytic cases and a slow loop, and
--train.lambda-depth-smooth in the trainer's loss."""

import math

import pytest
import torch

from builders import growing_tiny_config, make_toy_scene
from atgs.errors import UserError
from atgs.render import rasterize_gaussians
from atgs.train.losses import depth_smoothness
from atgs.train.trainer import Trainer

H, W = 24, 32


def _plane_depth(a: float, b: float, c: float) -> torch.Tensor:
    """(H, W) depth of a plane seen by a pinhole camera: its inverse depth is affine in (u, v)."""
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    return 1.0 / (a * u + b * v + c)


def test_zero_on_any_plane_and_positive_on_a_bump():
    alpha = torch.ones(H, W, dtype=torch.float64)
    image = torch.full((H, W, 3), 0.5, dtype=torch.float64)
    for a, b, c in ((0.0, 0.0, 0.5), (0.01, 0.0, 0.3), (0.003, 0.02, 0.2)):  # facing, slanted, a floor
        depth = _plane_depth(a, b, c)
        assert float(depth_smoothness(alpha, alpha * depth, image)) < 1e-12
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    bump = 2.0 - 0.5 * torch.exp(-((u - 16) ** 2 + (v - 12) ** 2) / 8.0)
    assert float(depth_smoothness(alpha, alpha * bump, image)) > 1e-3


def test_an_image_edge_at_a_depth_step_scales_its_terms_by_the_edge_weight():
    alpha = torch.ones(H, W, dtype=torch.float64)
    depth = torch.full((H, W), 2.0, dtype=torch.float64)
    depth[:, 16:] = 3.0  # a depth step between columns 15 and 16: only row terms see it
    flat = torch.full((H, W, 3), 0.5, dtype=torch.float64)
    edged = flat.clone()
    edged[:, 16:] += 0.1  # a colour change of 0.1 where the depth steps
    edge = 10.0
    plain = depth_smoothness(alpha, depth, flat, edge)
    weighted = depth_smoothness(alpha, depth, edged, edge)
    assert float(plain) > 0
    # both second differences that span the step see one pixel pair of colour change 0.1
    assert float(weighted) == pytest.approx(float(plain) * math.exp(-edge * 0.1), rel=1e-12)


def test_free_of_the_scenes_units_and_blind_to_the_background():
    torch.manual_seed(0)
    alpha = torch.rand(H, W, dtype=torch.float64) * 0.4 + 0.6
    depth = alpha * (2.0 + torch.rand(H, W, dtype=torch.float64))
    image = torch.rand(H, W, 3, dtype=torch.float64)
    ref = depth_smoothness(alpha, depth, image)
    assert float(depth_smoothness(alpha, 7.5 * depth, image)) == pytest.approx(float(ref), rel=1e-12)
    # pixels under min_alpha (the background): their depth does not matter
    alpha2 = alpha.clone()
    alpha2[:, :5] = 0.2
    depth2 = depth.clone()
    a = depth_smoothness(alpha2, depth2, image)
    depth2[:, :5] = torch.rand(H, 5, dtype=torch.float64) * 100
    assert float(depth_smoothness(alpha2, depth2, image)) == pytest.approx(float(a), rel=1e-12)


def test_gradient_matches_finite_differences_of_a_slow_loop():
    """The normalising mean is detached (a constant of the gradient, as in training), so the
    reference is the slow loop with that mean frozen at the evaluation point."""
    torch.manual_seed(1)
    h, w = 6, 7
    alpha = (torch.rand(h, w, dtype=torch.float64) * 0.3 + 0.7).requires_grad_(True)
    depth = (alpha.detach() * (2.0 + torch.rand(h, w, dtype=torch.float64))).requires_grad_(True)
    image = torch.rand(h, w, 3, dtype=torch.float64)
    ga, gd = torch.autograd.grad(depth_smoothness(alpha, depth, image), (alpha, depth))
    mean = (alpha / depth).mean().detach()
    eps = 1e-6
    for x, g, which in ((alpha, ga, 0), (depth, gd, 1)):
        num = torch.zeros_like(g)
        for i in range(h):
            for j in range(w):
                args = [alpha.detach().clone(), depth.detach().clone()]
                args[which][i, j] += eps
                hi = _loss_with_mean(*args, image, mean)
                args[which][i, j] -= 2 * eps
                lo = _loss_with_mean(*args, image, mean)
                num[i, j] = (hi - lo) / (2 * eps)
        assert torch.allclose(g, num, rtol=1e-5, atol=1e-8), (g - num).abs().max()


def _loss_with_mean(alpha, depth, image, mean):
    """depth_smoothness with the normalising mean given (a slow, explicit loop over pixels)."""
    inv = alpha / depth / mean
    h, w = inv.shape

    def g(y0: int, x0: int, y1: int, x1: int) -> torch.Tensor:  # colour change of one pixel pair
        return (image[y0, x0] - image[y1, x1]).abs().mean()

    tx = [(inv[y, x - 1] - 2 * inv[y, x] + inv[y, x + 1]).abs() * torch.exp(-10 * (g(y, x - 1, y, x) + g(y, x, y, x + 1)))
          for y in range(h) for x in range(1, w - 1)]
    ty = [(inv[y - 1, x] - 2 * inv[y, x] + inv[y + 1, x]).abs() * torch.exp(-10 * (g(y - 1, x, y, x) + g(y, x, y + 1, x)))
          for y in range(1, h - 1) for x in range(w)]
    return torch.stack(tx).mean() + torch.stack(ty).mean()


def test_equals_a_slow_loop_over_pixels():
    torch.manual_seed(2)
    h, w = 6, 7
    alpha = torch.rand(h, w, dtype=torch.float64) * 0.3 + 0.7
    depth = alpha * (2.0 + torch.rand(h, w, dtype=torch.float64))
    image = torch.rand(h, w, 3, dtype=torch.float64)
    mean = (alpha / depth).mean()
    assert float(depth_smoothness(alpha, depth, image)) == pytest.approx(float(_loss_with_mean(alpha, depth, image, mean)),
                                                                         rel=1e-12)


def test_the_trainer_adds_the_weighted_term_to_its_loss(tmp_path):
    scene = make_toy_scene(num_frames=4, num_cameras=5, width=40, height=32, keyframes=2)
    m, t = growing_tiny_config(10)
    torch.manual_seed(0)
    tr = Trainer(scene, m, t, tmp_path)
    for _ in range(5):
        tr.train_step()
    ci = tr.train_idx[0]
    cam, gt = tr.cams[ci], tr.images.get(ci, 0)
    with torch.no_grad():
        dec = tr.model.decode_frame(0, [cam], track=False)
        out = rasterize_gaussians(dec.gaussians, cam)
        tr.cfg.lambda_depth_smooth = 0.0
        without = float(tr.compute_loss(dec, out, gt))
        tr.cfg.lambda_depth_smooth, tr.cfg.depth_smooth_edge = 2.5, 4.0
        with_term = float(tr.compute_loss(dec, out, gt))
        term = float(depth_smoothness(out.alpha, out.depth, gt, 4.0))
    assert term > 0
    assert with_term - without == pytest.approx(2.5 * term, rel=1e-5)


@pytest.mark.parametrize("field,flag", [("lambda_depth_smooth", "lambda-depth-smooth"),
                                        ("lambda_distortion", "lambda-distortion")])
def test_a_negative_loss_weight_is_refused(tmp_path, field, flag):
    scene = make_toy_scene(num_frames=4, num_cameras=4, width=32, height=24, keyframes=2)
    m, t = growing_tiny_config(5)
    setattr(t, field, -1.0)
    with pytest.raises(UserError, match=flag):
        Trainer(scene, m, t, tmp_path)
