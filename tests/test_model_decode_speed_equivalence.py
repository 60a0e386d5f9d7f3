"""The cached inference decode (atgs.model.fast_decode) against the training decode path.

The reference is ``ATGSModel._decode(..., track=False)``, the code the trainer runs; the fast path
factors the 4D hash lookups into a spatial part and two time vertices, caches per-anchor
quantities and stacks the decoder heads' first layers, so results agree up to float32 round-off.
"""

from __future__ import annotations

import torch
from torch import nn

from builders import keyframe_point_model, randomize_features
from atgs.gaussians import Gaussians
from atgs.model.atgs_model import ATGSModel
from atgs.model.config import HashGridConfig
from atgs.train.config import preset
from atgs.model.fast_decode import InferenceCache, plain_heads
from atgs.model.grids import HashGrid4D

FIELDS = ("means", "quats", "scales", "opacities", "colors")


def _model(segments: int = 3, threshold: float = 0.0, F: int = 17, K: int = 5) -> ATGSModel:
    cfg, _ = preset("tiny")
    cfg.window, cfg.num_segments, cfg.opacity_threshold = 3, segments, threshold
    # base 2, growth 2: level 0 fits the 2^8 table (dense), levels 1-3 are hashed.
    cfg.hash = HashGridConfig(levels=4, features_per_level=2, log2_table_size=8, base_resolution=2,
                              growth=2.0, max_time_resolution=5, mlp_hidden=16)
    gen = torch.Generator().manual_seed(1)
    model = keyframe_point_model(cfg, F, K, 30, gen)
    randomize_features(model, gen)  # trained-looking: nonzero anchor features, F_s, larger hash values
    # Shrink the box so that some anchors fall outside it (zero grid features there).
    lo, hi = model.bbox_min.clone(), model.bbox_max.clone()
    model.bbox_min, model.bbox_max = lo + 0.2 * (hi - lo), hi - 0.2 * (hi - lo)
    return model


def _reference_frame(model: ATGSModel, f: int) -> Gaussians:
    return model.gaussians_at_frame_reference(f)


def _assert_same(a: Gaussians, b: Gaussians) -> None:
    for k in FIELDS:
        torch.testing.assert_close(getattr(a, k), getattr(b, k), rtol=1e-5, atol=2e-6, msg=k)


def test_toy_model_has_dense_and_hashed_levels_and_outside_anchors():
    model = _model()
    assert [model.hash.dense_level(lv) for lv in range(4)] == [True, False, False, False]
    xn = model.normalized_positions(model.anchor_mu)
    outside = ~((xn >= 0) & (xn <= 1)).all(1)
    assert 0 < int(outside.sum()) < model.num_anchors


def test_spatial_time_split_gives_the_4d_rows_and_weights_exactly():
    gen = torch.Generator().manual_seed(3)
    hg = HashGrid4D(3, 5, 2, 9, 2, 1.8, 4, generator=gen)
    assert any(hg.dense_level(lv) for lv in range(5)) and not all(hg.dense_level(lv) for lv in range(5))
    x = torch.rand(200, 3, generator=gen) * 1.4 - 0.2  # some outside [0, 1]
    x[:5] = torch.tensor([[0, 0, 0], [1, 1, 1], [0.5, 1, 0], [1, 0.25, 1], [0.999999, 0, 0.5]])
    for tau in (0.0, 0.13, 0.5, 0.77, 1.0):
        for grid in range(3):
            rows, w = hg.indices(x, tau, grid)  # (N, L, 16): corner bit 3 is the time offset
            for lv in range(hg.levels):
                partial, w3 = hg.spatial_slots(x, lv)
                v0, wt0, wt1 = hg.time_corners(tau, lv)
                assert torch.equal(hg.combine_time(partial, lv, v0, grid), rows[:, lv, :8])
                assert torch.equal(hg.combine_time(partial, lv, v0 + 1, grid), rows[:, lv, 8:])
                torch.testing.assert_close(w3 * wt0, w[:, lv, :8], rtol=1e-6, atol=1e-7)
                torch.testing.assert_close(w3 * wt1, w[:, lv, 8:], rtol=1e-6, atol=1e-7)


def test_fast_frames_equal_training_path_over_all_frames_and_segments():
    model = _model(segments=3)
    segs = {model.timeline.segment_of_frame(f) for f in range(model.num_frames)}
    assert segs == {0, 1, 2}
    for f in list(range(model.num_frames)) + [3, 0, 16]:  # revisits use the cache
        _assert_same(model.gaussians_at_frame(f), _reference_frame(model, f))


def test_fast_time_path_equals_training_path_between_frames():
    model = _model(segments=2)
    tl = model.timeline
    for t in (0.0, 0.031, 0.26, 0.5, 0.5001, 0.74, 1.0, 1.7, -0.3):
        f = tl.frame_at(t)
        m, tau = tl.segment_at(t)
        with torch.no_grad():
            want = model._decode(f, m, tau, None, track=False).gaussians
        _assert_same(model.gaussians_at(t), want)


def test_cache_follows_in_place_updates_and_replaced_tensors():
    model = _model()
    _assert_same(model.gaussians_at_frame(5), _reference_frame(model, 5))
    gen = torch.Generator().manual_seed(7)
    rows = torch.arange(0, model.hash.table.shape[0], 3)
    # In-place row updates as SparseAdam does them, then a dense Adam-like decoder step.
    model.hash.table.index_copy_(0, rows, torch.randn(rows.numel(), model.hash.table.shape[1], generator=gen))
    _assert_same(model.gaussians_at_frame(5), _reference_frame(model, 5))
    model.anchor_feature.index_copy_(0, torch.tensor([0, 2]), torch.randn(2, model.anchor_feature.shape[1]))
    model.spatial.table.add_(0.5)
    _assert_same(model.gaussians_at_frame(5), _reference_frame(model, 5))
    with torch.no_grad():
        for p in model.decoder.parameters():
            p.mul_(1.3)
    model.anchor_log_scale.sub_(0.2)
    _assert_same(model.gaussians_at_frame(5), _reference_frame(model, 5))
    # Anchor edits replace the tensors.
    n = model.num_anchors
    model.keep_anchors(torch.arange(n) % 3 != 0)
    _assert_same(model.gaussians_at_frame(9), _reference_frame(model, 9))
    model.add_anchors(torch.rand(4, 3), torch.randn(4, model.anchor_feature.shape[1]), torch.zeros(4, 6),
                      torch.tensor([0, 1, 2, 4]))
    _assert_same(model.gaussians_at_frame(9), _reference_frame(model, 9))
    model.set_sparse_tensor("hash", model.hash.table * 2)
    model.decoder.load_state_dict({k: v * 0.5 for k, v in model.decoder.state_dict().items()})
    _assert_same(model.gaussians_at_frame(11), _reference_frame(model, 11))


def test_reloaded_model_and_tiny_slice_cache_agree():
    model = _model()
    again = ATGSModel.from_state(model.cfg, model.state_dict(), model.num_frames, model.fps, model.cameras)
    again.inference_cache = InferenceCache(slice_cache_bytes=0)  # evicts down to 2 slices per level
    for f in range(model.num_frames):
        _assert_same(again.gaussians_at_frame(f), _reference_frame(model, f))


def test_opacity_threshold_drops_the_same_gaussians():
    probe = _model()
    opac = probe.gaussians_at_frame_reference(8).opacities.sort().values
    gaps = opac[1:] - opac[:-1]
    mid = opac.numel() // 4 + int(gaps[opac.numel() // 4: 3 * opac.numel() // 4].argmax())
    thr = float(opac[mid] + opac[mid + 1]) / 2  # far from every opacity: no round-off flips
    model = _model(threshold=thr)
    a, b = model.gaussians_at_frame(8), _reference_frame(model, 8)
    assert 0 < a.opacities.numel() < opac.numel()
    _assert_same(a, b)


def test_custom_decoder_heads_use_the_generic_path():
    model = _model()
    assert plain_heads(model.decoder) is not None
    head = model.decoder.color
    model.decoder.color = nn.Sequential(head[0], head[1], head[2], nn.Identity())
    assert plain_heads(model.decoder) is None
    _assert_same(model.gaussians_at_frame(7), _reference_frame(model, 7))
    model.decoder.color = nn.Sequential(head[0], nn.Tanh(), head[2])  # a different function
    _assert_same(model.gaussians_at_frame(7), _reference_frame(model, 7))


def test_no_active_anchor_gives_empty_gaussians():
    model = _model()
    model.keep_anchors(torch.zeros(model.num_anchors, dtype=torch.bool))
    g = model.gaussians_at_frame(4)
    assert g.means.shape == (0, 3) and g.opacities.shape == (0,)
    # the slice cache of 0-byte slices: one slot per (grid, level, time vertex) at most, where
    # its byte budget asked for 256 Mi of them (an 11 GB list of free slots, 95 s)
    hg = model.hash
    slices = {(m, lv, v) for m in range(hg.num_grids) for lv in range(hg.levels) for v in range(hg.time_res[lv] + 1)}
    pool = model.inference_cache._features.pool
    assert 2 * hg.levels <= pool.shape[0] <= max(len(slices), 2 * hg.levels)
