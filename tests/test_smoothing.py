"""3D smoothing filter (atgs.model.smoothing) against dense covariance algebra and a per-camera
loop; the model's two decode paths agree with it on."""

from __future__ import annotations

import math

import pytest
import torch

from atgs.model.smoothing import VIEW_MARGIN, filter_variance, sampling_rates, smooth
from atgs.train.config import preset
from builders import keyframe_point_model, randomize_features, ring_cameras


def _rotation(q: torch.Tensor) -> torch.Tensor:
    w, x, y, z = (q / q.norm()).double().tolist()
    return torch.tensor([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]], dtype=torch.float64)


def test_filtered_gaussian_is_the_covariance_plus_the_filter_with_its_mass_kept():
    gen = torch.Generator().manual_seed(0)
    A, q = 7, 3
    scales = torch.rand(A, q, 3, generator=gen, dtype=torch.float64) * 0.2 + 1e-3
    scales[0, 0, 2] = 1e-9  # a flat disk
    quats = torch.randn(A, q, 4, generator=gen, dtype=torch.float64)
    opac = torch.rand(A, q, generator=gen, dtype=torch.float64)
    var = torch.rand(A, generator=gen, dtype=torch.float64) * 0.01
    var[3] = 0.0  # not seen: unfiltered
    new_scales, new_opac = smooth(scales, opac, var)
    for a in range(A):
        for i in range(q):
            R = _rotation(quats[a, i])
            sigma = R @ torch.diag(scales[a, i] ** 2) @ R.T
            want = sigma + var[a] * torch.eye(3, dtype=torch.float64)
            got = R @ torch.diag(new_scales[a, i] ** 2) @ R.T
            torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-14)
            # opacity x sqrt(det) (the Gaussian's integral up to a constant) is kept
            # det(sigma) = prod(scale^2) (rotation-invariant; computed densely it loses the flat disk)
            ratio = math.sqrt(float(torch.prod(scales[a, i] ** 2)) / float(torch.linalg.det(want)))
            assert float(new_opac[a, i]) == pytest.approx(float(opac[a, i]) * ratio, rel=1e-6, abs=1e-12)
    assert torch.equal(new_scales[3], scales[3]) and torch.equal(new_opac[3], opac[3])


def test_filter_gradients_are_finite_and_match_finite_differences():
    gen = torch.Generator().manual_seed(1)
    scales = (torch.rand(5, 2, 3, generator=gen, dtype=torch.float64) * 0.1 + 0.01)
    scales[0, 0] = torch.tensor([1e-30, 0.05, 0.0], dtype=torch.float64)  # zero and tiny scales
    opac = torch.rand(5, 2, generator=gen, dtype=torch.float64)
    var = torch.tensor([1e-3, 0.0, 2e-3, 5e-4, 1e-2], dtype=torch.float64)
    scales.requires_grad_(True)
    opac.requires_grad_(True)
    s, o = smooth(scales, opac, var)
    (s.sum() + 3 * o.sum()).backward()
    assert bool(torch.isfinite(scales.grad).all()) and bool(torch.isfinite(opac.grad).all())
    safe = scales.detach().clone()
    safe[0, 0] = torch.tensor([0.02, 0.05, 0.03], dtype=torch.float64)
    torch.autograd.gradcheck(lambda x, y: smooth(x, y, var), (safe.requires_grad_(True), opac.detach().requires_grad_(True)))


def test_sampling_rates_match_a_per_camera_loop():
    cams = ring_cameras(5, (40, 30), radius=3.0)
    gen = torch.Generator().manual_seed(2)
    mu = torch.rand(300, 3, generator=gen) * 8 - 4  # some outside every view, some behind cameras
    rates = sampling_rates(mu, cams)
    for i in range(mu.shape[0]):
        best = 0.0
        for c in cams:
            uv, z = c.project(mu[i: i + 1].double().numpy())
            u, v = float(uv[0, 0]), float(uv[0, 1])
            mw, mh = VIEW_MARGIN * c.width, VIEW_MARGIN * c.height
            if z[0] > 0.01 and -mw < u < c.width + mw and -mh < v < c.height + mh:
                best = max(best, max(c.fx, c.fy) / float(z[0]))
        assert float(rates[i]) == pytest.approx(best, rel=1e-4), i
    assert bool((rates == 0).any()) and bool((rates > 0).any())
    var = filter_variance(rates, 0.2)
    seen = rates > 0
    torch.testing.assert_close(var[seen], 0.2 / rates[seen] ** 2)
    assert bool((var[~seen] == 0).all())


def _smoothed_model():
    cfg, _ = preset("tiny")
    cfg.window, cfg.num_segments, cfg.smoothing_3d, cfg.opacity_threshold = 3, 2, 0.5, 0.0
    gen = torch.Generator().manual_seed(5)
    model = keyframe_point_model(cfg, 17, 5, 20, gen)
    randomize_features(model, gen)
    model.anchor_velocity = 0.05 * torch.randn(model.num_anchors, 3, generator=gen)
    return model


def test_model_decodes_apply_the_filter_and_agree():
    model = _smoothed_model()
    plain = _smoothed_model()
    plain.cfg.smoothing_3d = 0.0
    var = model.smoothing_variance()
    assert var is not None and plain.smoothing_variance() is None and bool((var > 0).any())
    for f in (0, 5, 16):
        a, b = model.decode_frame(f, track=False), plain.decode_frame(f, track=False)
        assert torch.equal(a.active, b.active)
        want_s, want_o = smooth(b.raw.scales, b.raw.opacities, var[b.active])
        torch.testing.assert_close(a.raw.scales, want_s)
        torch.testing.assert_close(a.raw.opacities, want_o)
        fast, ref = model.gaussians_at_frame(f), model.gaussians_at_frame_reference(f)
        for k in ("means", "quats", "scales", "opacities", "colors"):
            torch.testing.assert_close(getattr(fast, k), getattr(ref, k), rtol=1e-5, atol=2e-6, msg=k)
    # the held-out cameras do not count: holding out the only camera that sees an anchor unfilters it
    model.test_camera_names = [model.cameras[0].name]
    others = model.cameras[1:]
    expect = filter_variance(sampling_rates(model.anchor_mu, others or model.cameras), 0.5)
    torch.testing.assert_close(model.smoothing_variance(), expect)


def test_training_with_the_filter_keeps_gaussians_no_thinner_than_it(tmp_path):
    from atgs.train.trainer import Trainer
    from builders import make_toy_scene

    scene = make_toy_scene(num_frames=5, num_cameras=4, width=40, height=30, keyframes=3)
    m, t = preset("tiny")
    m.smoothing_3d, t.iterations = 0.3, 20
    tr = Trainer(scene, m, t, tmp_path / "run")
    tr.train(progress=False, final_renders=False)
    model = tr.model
    var = model.smoothing_variance()
    dec = model.decode_frame(2, track=False)
    floor = var[dec.active].sqrt()[:, None, None]
    seen = floor > 0
    assert bool(seen.any())
    assert bool(((dec.raw.scales >= floor * (1 - 1e-5)) | ~seen).all())
    assert float(dec.raw.opacities.detach().max()) > 0
