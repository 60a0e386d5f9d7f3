"""Motion measurement (atgs.data.motion_measure) on tiny synthetic prepared scenes with known motion."""

from __future__ import annotations

import math

import numpy as np
import pytest

from atgs.auto_config import choose_config
from atgs.cameras import Camera, look_at
from atgs.data.motion_measure import (MotionConfig, box_downsample, estimate_noise, frame_difference, lag_steps,
                              measure_motion, point_spacing, turnover_time)
from atgs.data.scene import MemoryScene, PreparedScene, write_prepared_scene
from atgs.train.config import preset

W, H = 64, 48
KMAT = np.array([[50.0, 0, W / 2], [0, 50.0, H / 2], [0, 0, 1]])
CFG = MotionConfig(progress=False)


def _cams(n: int) -> list[Camera]:
    return [Camera(f"cam{i:02d}", W, H, KMAT, look_at(np.array([3 * np.cos(i), 3 * np.sin(i), 1.0]), np.zeros(3)))
            for i in range(n)]


def _background(ci: int) -> np.ndarray:
    """Static texture in [0.2, 0.8] (so added noise is not clipped), different per camera."""
    rng = np.random.default_rng(100 + ci)
    return (0.2 + 0.6 * rng.random((H, W, 3))).astype(np.float32)


def _square_x(f: int, x0: float, v: float, f0: int, f1: int) -> int:
    """Left edge of the square at frame f: moves at v px/frame during [f0, f1), still otherwise."""
    return int(round(x0 + v * (min(max(f, f0), f1) - f0)))


def _square_mask(f: int, a: int, y0: int, **motion) -> np.ndarray:
    m = np.zeros((H, W), bool)
    x = _square_x(f, **motion)
    m[y0:y0 + a, x:x + a] = True
    return m


def _write_scene(path, frames: int, cams: int = 2, square: dict | None = None, noise: float = 0.0,
                 keyframes=None) -> PreparedScene:
    bgs = [_background(c) for c in range(cams)]

    def frame(ci: int, f: int) -> np.ndarray:
        img = bgs[ci].copy()
        if square is not None:
            img[_square_mask(f, **square)] = (0.95, 0.05, 0.05)  # uniform: only its edges change
        if noise > 0:
            img = img + np.random.default_rng(1000 * ci + f).normal(0, noise, img.shape).astype(np.float32)
        return np.clip(img, 0, 1)

    rng = np.random.default_rng(0)
    pts = rng.random((200, 3)) * np.array([4.0, 2.0, 1.0])
    keyframes = sorted(set(keyframes or [0, frames - 1]))
    kf = np.arange(200) % len(keyframes)
    write_prepared_scene(path, MemoryScene(_cams(cams), frames, keyframes=keyframes, points=pts, point_keyframes=kf,
                                           point_colors=np.full((200, 3), 0.5)), frame)
    return PreparedScene.load(path)


# --- pure pieces ---------------------------------------------------------------------------------

def test_box_downsample_matches_slow_loop() -> None:
    img = np.random.default_rng(0).integers(0, 256, (23, 37, 3), dtype=np.uint8)
    out = box_downsample(img, 10)  # s = 4 -> (3, 5, 9)
    s = 4
    ref = np.zeros((3, 23 // s, 37 // s))
    for c in range(3):
        for y in range(23 // s):
            for x in range(37 // s):
                ref[c, y, x] = img[y * s:(y + 1) * s, x * s:(x + 1) * s, c].astype(np.float64).mean() / 255
    assert out.shape == ref.shape and out.dtype == np.float32
    np.testing.assert_allclose(out, ref, atol=1e-6)
    np.testing.assert_allclose(box_downsample(img, 64), img.transpose(2, 0, 1) / 255.0, atol=1e-7)


def test_frame_difference_is_channel_mean_abs() -> None:
    rng = np.random.default_rng(1)
    a, b = rng.random((2, 3, 4, 5)).astype(np.float32), rng.random((2, 3, 4, 5)).astype(np.float32)
    ref = np.mean(np.abs(a - b), axis=1)
    np.testing.assert_allclose(frame_difference(a, b), ref, atol=1e-6)


def test_turnover_time_analytic() -> None:
    lags = np.linspace(0.05, 60, 1200)
    # exponential saturation: integral time scale = tau
    assert turnover_time(lags, 0.3 * (1 - np.exp(-lags / 4.0))) == pytest.approx(4.0, rel=0.01)
    # linear ramp to a plateau at T (sampled exactly at the knee): T / 2
    L = np.array([1.0, 2, 3, 6, 10, 20])
    assert turnover_time(L, np.minimum(L, 6.0) * 0.01) == pytest.approx(3.0)
    # a periodic dip after saturation is ignored (running maximum)
    assert turnover_time(L, np.array([1, 2, 3, 6, 1, 6]) * 0.01) == pytest.approx(3.0)
    assert math.isinf(turnover_time(L, np.zeros(6)))


def test_lag_steps() -> None:
    assert lag_steps(2) == [1]
    s = lag_steps(64)
    assert s[:5] == [1, 2, 3, 4, 6] and s[-1] <= 63 and s == sorted(set(s))


def test_point_spacing_grid() -> None:
    g = np.stack(np.meshgrid(*[np.arange(6) * 0.25] * 3, indexing="ij"), -1).reshape(-1, 3)
    pts = np.concatenate([g, g + 10.0, g])  # duplicates must not give zero spacing
    kf = np.array([0] * len(g) + [1] * len(g) + [1] * len(g))
    assert point_spacing(pts, kf, 4096) == pytest.approx(0.25)


def test_noise_estimate_matches_monte_carlo() -> None:
    sigma = 0.02
    rng = np.random.default_rng(5)
    frames = rng.normal(0.5, sigma, (2, 31, 3, 20, 20)).astype(np.float32)
    diffs = frame_difference(frames[:, 1:], frames[:, :-1])
    # reference: median of the channel mean of 3 |N(0, 2 sigma^2)| from a large independent sample
    ref = np.median(np.abs(np.random.default_rng(9).normal(0, sigma * np.sqrt(2), (200000, 3))).mean(1))
    assert estimate_noise(diffs, 25.0) == pytest.approx(ref, rel=0.1)


# --- whole measurement on scenes -----------------------------------------------------------------

def test_static_scene(tmp_path) -> None:
    s = measure_motion(_write_scene(tmp_path / "s", 12), CFG)
    assert s.static and s.moving_fraction == 0.0 and s.time_scale == 12.0
    assert s.noise == 0.0 and s.threshold == pytest.approx(CFG.min_threshold)
    assert max(s.energy) == 0.0 and len(s.energy) == 11
    ch = choose_config(s, preset("cpu")[0])
    assert ch.overrides["num_keyframes"] == 1 and ch.overrides["num_segments"] == 1


def test_noisy_static_scene_is_static(tmp_path) -> None:
    sigma = 3.0 / 255
    s = measure_motion(_write_scene(tmp_path / "s", 16, noise=sigma), CFG)
    assert s.static and s.moving_fraction < 0.002
    # the noise floor is the median channel-mean |difference| of two noisy frames (+ uint8 rounding)
    ref = np.median(np.abs(np.random.default_rng(9).normal(0, sigma * np.sqrt(2), (200000, 3))).mean(1))
    assert s.noise == pytest.approx(ref, rel=0.25)


def test_moving_square_fraction_and_energy_location(tmp_path) -> None:
    F, f0, f1 = 40, 10, 20
    sq = dict(a=10, y0=15, x0=5.0, v=2.0, f0=f0, f1=f1)
    scene = _write_scene(tmp_path / "s", F, square=sq, noise=2.0 / 255)
    s = measure_motion(scene, CFG)
    # reference from geometry: pixels covered at some sampled frame but not at all of them
    masks = np.stack([_square_mask(f, **sq) for f in s.frames_used])
    truth = (masks.any(0) & ~masks.all(0)).mean()
    assert not s.static
    assert s.moving_fraction == pytest.approx(truth, rel=0.05)
    e = np.asarray(s.energy)
    mid = np.asarray(s.energy_frames)
    inside = (mid > f0) & (mid < f1)
    assert e[~inside].max() == 0.0 and e[inside].min() > 0
    assert f0 < s.motion_peak_frame < f1
    assert s.active_time_fraction == pytest.approx(inside.mean(), abs=1e-9)
    # energy by quarter: all the motion sits in frames 10..20 (quarters 2 and 3 of 0..39)
    parts = s.energy_by_part(4)
    assert parts[0] == 0 and parts[3] == 0 and sum(parts) == pytest.approx(1.0)


def test_faster_motion_shorter_time_scale(tmp_path) -> None:
    F, a = 40, 12
    res = {}
    for v in (1.0, 2.0):
        sq = dict(a=a, y0=15, x0=2.0, v=v, f0=0, f1=F)
        res[v] = measure_motion(_write_scene(tmp_path / f"v{v}", F, square=sq), CFG)
    # a uniform square moving v px/frame: changed area between frames L apart grows as 2 a v L
    # until L = a / v, then stays at 2 a^2 -> integral time scale a / (2 v)
    for v, s in res.items():
        assert s.time_scale == pytest.approx(a / (2 * v), rel=0.15)
    assert res[2.0].time_scale < res[1.0].time_scale
    base = preset("cpu")[0]
    slow, fast = (choose_config(res[v], base) for v in (1.0, 2.0))
    for knob in ("num_keyframes", "num_segments"):
        assert fast.wanted[knob] >= slow.wanted[knob]
        assert fast.overrides[knob] >= slow.overrides[knob]
    assert fast.wanted["num_keyframes"] > slow.wanted["num_keyframes"]


def test_deterministic_and_bounded_sample(tmp_path) -> None:
    sq = dict(a=8, y0=10, x0=3.0, v=1.0, f0=0, f1=30)
    scene = _write_scene(tmp_path / "s", 30, cams=3, square=sq)
    cfg = MotionConfig(max_cameras=2, max_frames=8, max_side=32, progress=False)
    a, b = measure_motion(scene, cfg).to_dict(), measure_motion(scene, cfg).to_dict()
    a.pop("seconds"), b.pop("seconds")
    assert a == b
    assert len(a["cameras_used"]) == 2 and len(a["frames_used"]) == 8 and a["image_size"] == (32, 24)
    assert a["frames_used"][0] == 0 and a["frames_used"][-1] == 29


def test_single_frame_scene(tmp_path) -> None:
    s = measure_motion(_write_scene(tmp_path / "s", 1, keyframes=[0]), CFG)
    assert s.static and s.num_frames == 1 and s.energy == [] and s.time_scale == 1.0
    ch = choose_config(s, preset("cpu")[0])
    assert ch.overrides["num_keyframes"] == 1 and ch.overrides["num_segments"] == 1


def test_scene_extent_and_spacing(tmp_path) -> None:
    s = measure_motion(_write_scene(tmp_path / "s", 3), CFG)
    assert s.points_extent == pytest.approx(4.0, abs=0.1)  # points span [0,4]x[0,2]x[0,1]
    assert s.extent == pytest.approx(float(np.max(s.bounds_size)))
    assert s.camera_spread > 0 and s.num_points == 200 and s.points_per_keyframe == 100
    assert 0 < s.point_spacing < 1.0


def test_bad_config() -> None:
    with pytest.raises(ValueError, match="max_frames"):
        MotionConfig(max_frames=1).validate()


def test_compression_like_flicker_is_not_motion(tmp_path) -> None:
    """Lossy video: static pixels are mostly unchanged but some jump by a few levels (block
    artifacts); such sparse jumps below ``min_threshold`` must not count as motion."""
    bg = _background(0)
    rng = np.random.default_rng(3)
    jumps = rng.random((20, H, W)) < 0.1  # 10% of the pixels jump in each frame
    levels = rng.choice([-4, -2, 2, 4], size=(20, H, W, 1)) / 255.0  # up to 8/255 between frames

    def frame(ci: int, f: int) -> np.ndarray:
        return np.clip(bg + jumps[f, ..., None] * levels[f], 0, 1)

    write_prepared_scene(tmp_path / "s", MemoryScene(_cams(1), 20), frame)
    s = measure_motion(PreparedScene.load(tmp_path / "s"), CFG)
    assert s.noise == 0.0  # most pixels never change: the noise floor cannot see the jumps
    assert s.static and s.moving_fraction == 0.0
