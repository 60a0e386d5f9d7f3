"""--auto rules (atgs.auto_config): paper calibration, monotonicity, bounds at the extremes."""

from __future__ import annotations

import dataclasses

import math

import pytest

from atgs.auto_config import AutoRules, apply_overrides, choose_config, format_choice
from atgs.data.motion_measure import MotionStats
from atgs.config_dict import to_dict
from atgs.model.config import ModelConfig
from atgs.train.config import preset
from atgs.timeline import Timeline

KNOBS = ("num_keyframes", "num_segments", "hash.log2_table_size", "spatial_resolution")
FREE = AutoRules(respect_scene_keyframes=False, memory_mb=1e6)  # no caps: the pure motion rules


def stats(moving: float = 0.2, tau: float = 5.0, frames: int = 120, static: bool | None = None,
          scene_keyframes: int = 10_000, spacing: float = 0.1, points_extent: float = 4.0,
          extent: float = 5.0, points_per_keyframe: float = 2000.0) -> MotionStats:
    static = moving < 2e-3 if static is None else static
    return MotionStats(
        num_frames=frames, fps=30.0, scene_keyframes=scene_keyframes, cameras_used=["a"],
        frames_used=[0, frames - 1], image_size=(64, 48), noise=0.0, threshold=2 / 255,
        moving_fraction=moving, moving_fraction_per_camera=[moving], energy=[], energy_frames=[],
        lags=[], changed_at_lag=[], time_scale=float(frames) if static else tau, static=static,
        active_time_fraction=0.0 if static else 1.0, bounds_size=[extent] * 3, extent=extent,
        points_extent=points_extent, camera_spread=3.0, point_spacing=spacing, num_points=10_000,
        points_per_keyframe=points_per_keyframe)


def test_paper_calibration() -> None:
    base = preset("paper")[0]
    # N3DV: 300 frames, slow motion (content turns over in ~20 frames): paper K=15, M=2
    n3dv = choose_config(stats(moving=0.1, tau=20.0, frames=300), base, FREE)
    assert n3dv.overrides["num_keyframes"] == 15 and n3dv.overrides["num_segments"] == 2
    # VRU: 250 frames, fast motion (turnover ~1 frame): paper K=250, M=12 (code: a grid per 20 frames)
    vru = choose_config(stats(moving=0.3, tau=1.0, frames=250), base, FREE)
    assert vru.overrides["num_keyframes"] == 250 and vru.overrides["num_segments"] == 13


def test_one_override_and_reason_per_knob() -> None:
    ch = choose_config(stats(), preset("cpu")[0])
    assert tuple(ch.overrides) == KNOBS
    assert len(ch.reasons) == len(KNOBS)
    for knob, line in zip(KNOBS, ch.reasons):
        assert line.startswith(f"{knob} = {ch.overrides[knob]}: ")
    text = format_choice(ch)
    assert all(k in text for k in KNOBS) and "turns over every 5.0 frames" in text


def test_static_and_single_frame_are_minimal() -> None:
    base = preset("cpu")[0]
    for s in (stats(moving=0.0), stats(moving=0.0, frames=1), stats(moving=0.5, frames=1, static=True)):
        ch = choose_config(s, base)
        assert ch.overrides["num_keyframes"] == 1 and ch.overrides["num_segments"] == 1
        assert ch.overrides["hash.log2_table_size"] == base.hash.log2_table_size - 4


@pytest.mark.parametrize("frames", [1, 2, 3, 120, 10_000])
@pytest.mark.parametrize("moving,tau", [(0.0, 1.0), (1e-3, 1.0), (1.0, 1.0), (1.0, 0.5), (0.3, 1e4)])
@pytest.mark.parametrize("name", ["tiny", "cpu", "paper"])
def test_bounds_at_extremes(frames: int, moving: float, tau: float, name: str) -> None:
    rules = AutoRules()
    base = preset(name)[0]
    s = stats(moving=moving, tau=min(tau, frames), frames=frames, scene_keyframes=min(frames, 6))
    ch = choose_config(s, base, rules)
    o = ch.overrides
    assert 1 <= o["num_keyframes"] <= min(frames, 6)
    assert 1 <= o["num_segments"] <= min(frames, rules.max_segments)
    if frames == 1 or s.static:  # nothing moves: one keyframe, one temporal grid
        assert (o["num_keyframes"], o["num_segments"]) == (1, 1)
    else:  # the documented rule, written out: >= 2 keyframes when anything moves, then the caps
        F, ts = frames, min(tau, frames)
        want = max(2, math.ceil(rules.keyframes_per_turnover * F / ts), math.ceil((F - 1) / rules.max_keyframe_gap) + 1)
        assert o["num_keyframes"] == min(want, F, rules.max_keyframes, 6)
        seg = max(float(rules.min_segment_frames), rules.segment_turnovers * ts)
        assert o["num_segments"] <= min(math.ceil(F / seg), F, rules.max_segments)  # memory may lower it
    t = o["hash.log2_table_size"]
    assert max(10, base.hash.log2_table_size - 4) <= t <= base.hash.log2_table_size + 2
    assert 8 <= o["spatial_resolution"] <= 256
    # memory budgets hold (parameters + 2 Adam moments, float32)
    h, d = base.hash, base.feature_dim
    grid = h.levels * 2**t * h.features_per_level + h.levels * h.features_per_level * h.mlp_hidden \
        + h.mlp_hidden + h.mlp_hidden * d + d
    assert o["num_segments"] * grid * 12 <= rules.memory_mb * 2**20 * rules.temporal_share
    assert o["spatial_resolution"] ** 3 * d * 12 <= rules.memory_mb * 2**20 * rules.spatial_share
    # the result is a valid model configuration
    cfg = apply_overrides(base, o)
    tl = Timeline(frames, cfg.num_keyframes, cfg.window, cfg.num_segments)
    assert tl.num_keyframes == o["num_keyframes"]


def test_monotone_in_motion_speed_and_length() -> None:
    base = preset("cpu")[0]
    for rules in (FREE, AutoRules(), AutoRules(memory_mb=64)):
        taus = [0.5, 1, 2, 3, 5, 8, 13, 20, 40, 80, 119]
        for knob in ("num_keyframes", "num_segments"):
            vals = [choose_config(stats(tau=t), base, rules).overrides[knob] for t in taus]
            assert vals == sorted(vals, reverse=True), (knob, vals)
            frames = [2, 5, 30, 60, 120, 500, 2000, 10_000]
            vals = [choose_config(stats(tau=min(4.0, f), frames=f), base, rules).overrides[knob] for f in frames]
            assert vals == sorted(vals), (knob, vals)
    fast = choose_config(stats(tau=1.0), base, FREE).overrides
    slow = choose_config(stats(tau=40.0), base, FREE).overrides
    assert fast["num_keyframes"] > slow["num_keyframes"] and fast["num_segments"] > slow["num_segments"]


def test_table_monotone_in_moving_content() -> None:
    base = preset("cpu")[0]
    fr = [0.0, 1e-3, 0.01, 0.05, 0.1, 0.25, 0.5, 1.0]
    vals = [choose_config(stats(moving=m), base, FREE).overrides["hash.log2_table_size"] for m in fr]
    assert vals == sorted(vals) and vals[0] < vals[-1]
    # the preset's size at the reference fraction, doubled per doubling of the moving fraction
    b = base.hash.log2_table_size
    assert choose_config(stats(moving=0.25), base, FREE).overrides["hash.log2_table_size"] == b
    assert choose_config(stats(moving=0.5), base, FREE).overrides["hash.log2_table_size"] == b + 1
    assert choose_config(stats(moving=0.0625), base, FREE).overrides["hash.log2_table_size"] == b - 2


def test_spatial_resolution_from_extent_and_spacing() -> None:
    base = preset("cpu")[0]  # bbox_padding 0.1, random_anchors > 0 -> the anchor box is the scene bounds
    ch = choose_config(stats(extent=5.0, spacing=0.1), base, FREE)
    assert ch.overrides["spatial_resolution"] == 5.0 * 1.2 / 0.1 + 1  # 61 vertices = 60 cells of 0.1
    no_random = dataclasses.replace(base, random_anchors=0)
    assert choose_config(stats(points_extent=4.0, spacing=0.1), no_random, FREE).overrides["spatial_resolution"] == 49
    ext = [0.5, 1, 2, 4, 8, 16, 64]
    vals = [choose_config(stats(extent=e), base).overrides["spatial_resolution"] for e in ext]
    assert vals == sorted(vals) and vals[0] == 8  # lower bound
    sp = [1e-4, 1e-3, 0.01, 0.05, 0.1, 1.0]
    vals = [choose_config(stats(spacing=x), base).overrides["spatial_resolution"] for x in sp]
    assert vals == sorted(vals, reverse=True)
    # no points: keep the preset's resolution
    assert choose_config(stats(spacing=0.0, points_extent=0.0), base).overrides["spatial_resolution"] \
        == base.spatial_resolution


def test_scene_keyframes_cap_and_advice() -> None:
    ch = choose_config(stats(tau=2.0, frames=120, scene_keyframes=6), preset("cpu")[0])
    assert ch.overrides["num_keyframes"] == 6 and ch.wanted["num_keyframes"] == 60
    assert "atgs-prepare with --keyframes 60" in ch.reasons[0]
    free = choose_config(stats(tau=2.0, frames=120, scene_keyframes=6), preset("cpu")[0],
                         AutoRules(respect_scene_keyframes=False))
    assert free.overrides["num_keyframes"] == 60


def test_keyframe_gap_floor() -> None:
    # slow motion in a long sequence still gets a keyframe at least every 60 frames
    ch = choose_config(stats(tau=1000.0, frames=1201), preset("cpu")[0], FREE)
    assert ch.overrides["num_keyframes"] == 21


def test_memory_caps_reduce_table_then_segments() -> None:
    base = preset("paper")[0]  # 16 levels x 8 features: 2^16 -> 32 MB per table
    ch = choose_config(stats(tau=1.0, frames=10_000, moving=0.25), base, AutoRules(memory_mb=1024))
    o = ch.overrides
    assert o["hash.log2_table_size"] == 12  # reduced to the lower bound first (base 16 - 4)
    assert o["num_segments"] < ch.wanted["num_segments"]
    assert "temporal-grid memory" in ch.reasons[1] and "reduced to 2^12" in ch.reasons[2]


def test_base_as_dict_and_deterministic() -> None:
    base = preset("cpu")[0]
    a = choose_config(stats(), base)
    b = choose_config(stats(), to_dict(base))
    assert a == b and choose_config(stats(), base) == a


def test_frames_per_segment_is_cleared() -> None:
    base = dataclasses.replace(preset("cpu")[0], frames_per_segment=20)
    ch = choose_config(stats(), base)
    assert ch.overrides["frames_per_segment"] == 0 and len(ch.reasons) == 5


def test_apply_overrides() -> None:
    base = ModelConfig()
    cfg = apply_overrides(base, {"num_keyframes": 7, "hash.log2_table_size": 12})
    assert cfg.num_keyframes == 7 and cfg.hash.log2_table_size == 12
    assert base.num_keyframes == 0 and base.hash.log2_table_size == 16  # base untouched
    with pytest.raises(ValueError, match="nope"):
        apply_overrides(base, {"nope": 1})
    with pytest.raises(ValueError, match="hash.nope"):
        apply_overrides(base, {"hash.nope": 1})


def test_bad_rules() -> None:
    with pytest.raises(ValueError, match="memory_mb"):
        choose_config(stats(), ModelConfig(), AutoRules(memory_mb=0))
    with pytest.raises(TypeError, match="ModelConfig"):
        choose_config(stats(), 3)  # type: ignore[arg-type]
