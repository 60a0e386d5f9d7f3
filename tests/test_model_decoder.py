"""Decoder heads (shapes, activations, the SPEC formulas) and model-level behaviour."""

import numpy as np
import pytest
import torch

from builders import keyframe_point_model
from atgs.train.config import preset
from atgs.model.decoder import GaussianDecoder


def test_decoder_heads_follow_spec_formulas():
    torch.manual_seed(0)
    dec = GaussianDecoder(in_dim=8, q=3, hidden_opacity=5, hidden_cov=6, hidden_color=7, hidden_offset=9)
    assert dec.offset[0].out_features == 9 and dec.cov[2].out_features == 21 and dec.color[2].out_features == 9
    fw = torch.randn(4, 8) * 3
    mu = torch.randn(4, 3)
    v = torch.randn(4, 6) * 0.5
    out = dec(fw, mu, v)
    assert out.means.shape == (4, 3, 3) and out.quats.shape == (4, 3, 4) and out.scales.shape == (4, 3, 3)
    assert out.opacities.shape == (4, 3) and out.colors.shape == (4, 3, 3)
    # opacity / colour: sigmoid of the head output
    torch.testing.assert_close(out.opacities, torch.sigmoid(dec.opacity(fw)))
    torch.testing.assert_close(out.colors, torch.sigmoid(dec.color(fw)).view(4, 3, 3))
    # mean = mu + offset * exp(v[:3]); scale = exp(v[3:]) * sigmoid(.); rotation normalized
    off = dec.offset(fw).view(4, 3, 3)
    torch.testing.assert_close(out.means, mu[:, None] + off * v[:, None, :3].exp())
    cov = dec.cov(fw).view(4, 3, 7)
    torch.testing.assert_close(out.scales, v[:, None, 3:].exp() * torch.sigmoid(cov[..., :3]))
    torch.testing.assert_close(out.quats.norm(dim=-1), torch.ones(4, 3))
    torch.testing.assert_close(out.quats, cov[..., 3:] / cov[..., 3:].norm(dim=-1, keepdim=True))


def _toy_model(window=3, static=True, K=4, F=13, **kw):
    m, _ = preset("tiny")
    m.window, m.static_keyframe0, m.anchor_layout = window, static, "per-keyframe"
    for k, v in kw.items():
        setattr(m, k, v)
    return keyframe_point_model(m, F, K, 40, torch.Generator().manual_seed(0))


def test_active_anchors_follow_window_and_static_flag():
    model = _toy_model(window=3, static=True)
    k = model.anchor_keyframe
    for f in range(model.num_frames):
        lo, hi = model.timeline.window_of_frame(f)
        want = ((k >= lo) & (k <= hi)) | (k == 0)
        assert torch.equal(model.active_anchors(f), want)
    model = _toy_model(window=3, static=False)
    last = model.num_frames - 1
    assert not model.active_anchors(last)[model.anchor_keyframe == 0].any()
    model = _toy_model(window=0)
    assert model.active_anchors(5).all()


@pytest.mark.parametrize("fade", [False, True])
def test_gaussians_at_time_and_frame_agree_and_count(fade):
    model = _toy_model(temporal_fade=fade)
    q = model.cfg.gaussians_per_anchor
    for f in (0, 4, 12):
        a = model.gaussians_at_frame(f)
        b = model.gaussians_at(f / (model.num_frames - 1))
        active = model.active_anchors(f).nonzero().squeeze(1)
        # with the fade, anchors faded below the cut are not decoded; without it, all are
        shown = int((model.fade_of(f, active)[1] >= model.fade_cut()).sum())
        if not fade:
            assert shown == len(active)
        assert shown > 0
        assert len(a) == q * shown
        for x, y in zip(a.as_tuple(), b.as_tuple()):
            torch.testing.assert_close(x, y)
        assert not a.means.requires_grad
        assert (a.opacities > 0).all() and (a.opacities < 1).all()
        assert ((a.colors > 0) & (a.colors < 1)).all()
    assert len(model.gaussians_at(-3.0)) == len(model.gaussians_at_frame(0))
    assert model.window_at(2.0) == model.timeline.window_of_frame(12)


def test_spatial_grid_ablation_and_zero_init():
    on = _toy_model(use_spatial_grid=True)
    off = _toy_model(use_spatial_grid=False)
    # F_s starts at zero, so both decode identically before training
    for x, y in zip(on.gaussians_at_frame(3).as_tuple(), off.gaussians_at_frame(3).as_tuple()):
        torch.testing.assert_close(x, y)
    dec = on.decode_frame(3, track=True)
    assert "spatial" in {s.name for s in dec.sparse}
    assert "spatial" not in {s.name for s in off.decode_frame(3, track=True).sparse}


def test_tracked_decode_touches_only_active_rows_and_sampled_segment():
    model = _toy_model()
    f = model.num_frames - 1
    dec = model.decode_frame(f, track=True)
    dec.gaussians.colors.sum().backward()
    names = {s.name: s for s in dec.sparse}
    active = model.active_anchors(f).nonzero().squeeze(1)
    active = active[model.fade_of(f, active)[1] >= model.fade_cut()]
    assert torch.equal(names["anchor_feature"].rows, active)
    assert names["tmlp_w1"].rows.tolist() == [model.timeline.segment_of_frame(f)]
    per_grid = model.hash.levels * model.hash.table_size
    assert (names["hash"].rows // per_grid == dec.segment).all()
    assert names["hash"].leaf.grad is not None and names["anchor_feature"].leaf.grad.abs().sum() > 0


def test_frustum_culling_drops_anchors_behind_camera():
    model = _toy_model()
    cam = model.cameras[0]
    model.refresh_reach()
    model.reach.settled.zero_()  # reach 0: the test is the centre's
    vis = model.visible_anchors(0, [cam])
    uv, z = cam.project(model.anchor_mu.numpy())
    inside = (z > 0.01) & (uv[:, 0] > -0.15 * 32) & (uv[:, 0] < 32 * 1.15) & (uv[:, 1] > -0.15 * 24) & (uv[:, 1] < 24 * 1.15)
    assert np.array_equal(vis.numpy(), inside)
    model.refresh_reach()
    dec = model.decode_frame(0, cam, track=False)
    assert set(dec.active.tolist()) <= set(model.visible_anchors(0, [cam]).nonzero().squeeze(1).tolist())


@pytest.mark.parametrize("K_model,expected", [(2, 2), (4, 4)])
def test_fewer_keyframes_than_scene(K_model, expected):
    model = _toy_model(num_keyframes=K_model)
    assert model.num_keyframes == expected
    assert int(model.anchor_keyframe.max()) == expected - 1
