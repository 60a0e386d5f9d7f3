"""Both decodes against an independent float64 decode (tests/decode_reference.py, from the SPEC's
formulas): the inference decode (``gaussians_at*``, cached) and the training decode
(``decode_frame``: tracked sparse leaves, with and without the frustum cull), with every
per-Gaussian feature on: the heads, 3D smoothing, temporal fade, velocity, opacity cut and
camera clearance."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from builders import randomize_features, side_camera
from decode_reference import ReferenceFrame, reference_frame
from atgs.cameras import Camera, look_at
from atgs.model.atgs_model import ATGSModel
from atgs.model.config import HashGridConfig
from atgs.timeline import evenly_spaced
from atgs.train.config import preset

FIELDS = ("means", "quats", "scales", "opacities", "colors")
F, K = 17, 5

CASES = {
    "plain": dict(temporal_fade=False, anchor_velocity=False, opacity_threshold=0.0, camera_clearance=0.0),
    "motion": dict(temporal_fade=True, anchor_velocity=True, opacity_threshold=0.0, camera_clearance=0.0),
    "everything": dict(temporal_fade=True, anchor_velocity=True, smoothing_3d=0.2, camera_clearance=0.25),
    "per-keyframe": dict(anchor_layout="per-keyframe", static_keyframe0=True, temporal_fade=True,
                         anchor_velocity=True, smoothing_3d=0.2),
}


def _model(case: str) -> ATGSModel:
    cfg, _ = preset("tiny")
    cfg.window, cfg.num_segments, cfg.frustum_cull = 3, 3, True
    # base 2, growth 2: level 0 fits the 2^8 table (dense), levels 1-3 are hashed
    cfg.hash = HashGridConfig(levels=4, features_per_level=2, log2_table_size=8, base_resolution=2,
                              growth=2.0, max_time_resolution=5, mlp_hidden=16)
    for k, v in CASES[case].items():
        setattr(cfg, k, v)
    gen = torch.Generator().manual_seed(1)
    pts = torch.rand(30 * K, 3, generator=gen)
    # a second camera inside the cloud: the clearance cuts Gaussians around it
    inner = Camera("inner", 32, 24, np.array([[30, 0, 16], [0, 30, 12], [0, 0, 1.0]]),
                   look_at(np.array([0.5, 0.5, 0.5]), np.array([2.0, 0.5, 0.5])))
    model = ATGSModel.from_points(cfg, pts, torch.arange(K).repeat_interleave(30), evenly_spaced(F, K), F, 25.0,
                                  [side_camera(), inner], seed=0)
    randomize_features(model, gen)
    model.anchor_log_scale = model.anchor_log_scale + 0.3 * torch.randn(model.anchor_log_scale.shape, generator=gen)
    model.anchor_velocity = 0.05 * torch.randn(model.anchor_velocity.shape, generator=gen)
    model.anchor_fade = model.anchor_fade + 0.5 * torch.randn(model.anchor_fade.shape, generator=gen)
    lo, hi = model.bbox_min.clone(), model.bbox_max.clone()  # some anchors outside the grids' box
    model.bbox_min, model.bbox_max = lo + 0.2 * (hi - lo), hi - 0.2 * (hi - lo)
    if case == "everything":  # an opacity cut far from every opacity: no round-off flips
        opac = reference_frame(model, 8).opacities.sort().values
        gaps = opac[1:] - opac[:-1]
        mid = opac.numel() // 4 + int(gaps[opac.numel() // 4: 3 * opac.numel() // 4].argmax())
        model.cfg.opacity_threshold = float(opac[mid] + opac[mid + 1]) / 2
    return model


def _assert_matches(ref: ReferenceFrame, got, anchor_ids=None, slot_ids=None) -> None:
    assert got.means.shape[0] == ref.means.shape[0] > 0
    for k in FIELDS:
        torch.testing.assert_close(getattr(got, k).double(), getattr(ref, k), rtol=1e-4, atol=2e-5, msg=k)
    if anchor_ids is not None:
        assert torch.equal(anchor_ids, ref.anchor_ids) and torch.equal(slot_ids, ref.slot_ids)


@pytest.fixture(scope="module", params=list(CASES))
def model(request) -> ATGSModel:
    return _model(request.param)


def test_the_cases_exercise_every_step(model) -> None:
    """Anchors outside the box, faded-out anchors, Gaussians cut ("everything"): each step has
    something to do."""
    xn = model.normalized_positions(model.anchor_mu)
    assert 0 < int((~((xn >= 0) & (xn <= 1)).all(1)).sum()) < model.num_anchors
    full = reference_frame(model, 8)
    assert full.means.shape[0] > 0
    if model.cfg.temporal_fade:
        active = model.active_anchors(8).nonzero().squeeze(1)
        assert full.anchor_ids.unique().numel() < active.numel(), "some anchors are faded out"
    if model.cfg.camera_clearance == CASES["everything"]["camera_clearance"]:
        drawn = full.means.shape[0]
        assert drawn < full.anchor_ids.unique().numel() * model.cfg.gaussians_per_anchor
        model.clearance.radius, kept = 0.0, model.clearance.radius
        assert reference_frame(model, 8).means.shape[0] > drawn, "the clearance cuts some"
        model.clearance.radius = kept


def test_inference_decode_matches_the_reference(model) -> None:
    for f in list(range(F)) + [3, 16]:  # revisits come from the cache
        _assert_matches(reference_frame(model, f), model.gaussians_at_frame(f))
    for t in (0.031, 0.26, 0.5001, 0.74, 1.0):
        _assert_matches(reference_frame(model, t=t), model.gaussians_at(t))


def test_training_decode_matches_the_reference(model) -> None:
    for f in range(F):
        d = model.decode_frame(f, track=True)
        assert d.sparse and d.gaussians.means.requires_grad
        _assert_matches(reference_frame(model, f), d.gaussians, d.anchor_ids, d.slot_ids)
        _assert_matches(reference_frame(model, f), model.gaussians_at_frame_reference(f))


def test_culled_training_decode_is_the_reference_on_the_anchors_it_keeps(model) -> None:
    model.refresh_reach()
    cam = side_camera(eye=(0.5, -3.0, 0.5), target=(4.0, 0.5, 0.5))  # sees part of the cloud
    for f in (0, 7, 16):
        d = model.decode_frame(f, cam, track=True)
        ref = reference_frame(model, f)
        kept = torch.isin(ref.anchor_ids, d.active)
        assert 0 < int(kept.sum()) < ref.anchor_ids.numel(), "the cull keeps some anchors, not all"
        part = ReferenceFrame(*(getattr(ref, k)[kept] for k in (*FIELDS, "anchor_ids", "slot_ids")))
        _assert_matches(part, d.gaussians, d.anchor_ids, d.slot_ids)
