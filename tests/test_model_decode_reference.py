"""Both decodes against an independent float64 decode (tests/decode_reference.py, from the SPEC's
formulas): the inference decode (``gaussians_at*``, cached) and the training decode
(``decode_frame``: tracked sparse leaves, with and without the frustum cull), with every
per-Gaussian feature on: the heads, 3D smoothing, temporal fade, velocity, opacity cut and
camera clearance."""

from __future__ import annotations

import pytest
import torch

from builders import DECODE_CASES, DECODE_FRAMES, DECODE_KEYFRAMES, decode_case_model, side_camera
from decode_reference import ReferenceFrame, reference_frame
from atgs.model.atgs_model import ATGSModel

FIELDS = ("means", "quats", "scales", "opacities", "colors")
F, K = DECODE_FRAMES, DECODE_KEYFRAMES

def _assert_matches(ref: ReferenceFrame, got, anchor_ids=None, slot_ids=None) -> None:
    assert got.means.shape[0] == ref.means.shape[0] > 0
    for k in FIELDS:
        torch.testing.assert_close(getattr(got, k).double(), getattr(ref, k), rtol=1e-4, atol=2e-5, msg=k)
    if anchor_ids is not None:
        assert torch.equal(anchor_ids, ref.anchor_ids) and torch.equal(slot_ids, ref.slot_ids)


@pytest.fixture(scope="module", params=list(DECODE_CASES))
def model(request) -> ATGSModel:
    return decode_case_model(request.param)


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
    if model.cfg.camera_clearance == DECODE_CASES["everything"]["camera_clearance"]:
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
