"""Timeline and evenly_spaced vs brute force over exact rationals (paper formulas, 1-based as
written), and the keyframe rule shared by atgs-prepare and the model."""

from fractions import Fraction

import numpy as np
import pytest

from atgs.timeline import Timeline, evenly_spaced, frame_at, time_of_frame


def paper_window(t: Fraction, K: int, W: int) -> tuple[int, int]:
    """Paper: h = floor(W/2), kbar = argmin_j |t(K-1) + 1 - j| (j = 1..K, first minimum),
    window [max(1, kbar-h), min(K, kbar+h)]; returned 0-based."""
    h = W // 2
    dists = [abs(t * (K - 1) + 1 - j) for j in range(1, K + 1)]
    kbar = 1 + dists.index(min(dists))
    return max(1, kbar - h) - 1, min(K, kbar + h) - 1


@pytest.mark.parametrize("F,K,W", [(250, 250, 7), (250, 12, 5), (31, 4, 3), (9, 1, 7), (9, 3, 9), (7, 7, 1),
                                   (2, 2, 3), (1, 1, 7), (20, 7, 2)])
def test_window_matches_paper_formula(F, K, W):
    tl = Timeline(F, K, W, 2)
    for f in range(F):
        t = Fraction(f, F - 1) if F > 1 else Fraction(0)
        assert tl.window_of_frame(f) == paper_window(t, K, W), (f, F, K, W)
        assert tl.window_at(float(t)) == tl.window_of_frame(f)


def test_window_special_cases():
    assert Timeline(100, 5, 11, 1).window_of_frame(50) == (0, 4)  # W > K: everything
    assert Timeline(100, 1, 7, 1).window_of_frame(99) == (0, 0)  # K = 1
    assert Timeline(100, 10, 1, 1).window_of_frame(99) == (9, 9)  # W = 1: one keyframe
    assert Timeline(100, 10, 0, 1).window_of_frame(3) == (0, 9)  # no window


def test_ten_thousand_frames_map_exactly():
    F, K, M = 10_000, 250, 12
    tl = Timeline(F, K, 7, M)
    f = np.arange(F, dtype=np.int64)
    # keyframe j at round(j (F-1)/(K-1)), half up, exact
    for j in range(K):
        assert tl.keyframe_frame(j) == int(Fraction(j * (F - 1), K - 1) + Fraction(1, 2))
    # nearest keyframe: argmin_j |f (K-1) - j (F-1)| in integers, first minimum
    d = np.abs(f[:, None] * (K - 1) - np.arange(K)[None, :] * (F - 1))
    kbar = d.argmin(axis=1)
    got = np.array([tl.nearest_keyframe_of_frame(int(i)) for i in f])
    assert np.array_equal(got, kbar)
    # segment m = floor(M f / (F-1)) clamped, local time exact
    seg = np.minimum(M - 1, (M * f) // (F - 1))
    assert np.array_equal([tl.segment_of_frame(int(i)) for i in f], seg)
    for i in (0, 1, 833, 834, 5000, 9998, 9999):
        m = int(seg[i])
        assert tl.local_time_of_frame(i) == pytest.approx(float(Fraction(M * i, F - 1) - m), abs=1e-15)
    # time <-> frame round trip and segments partition the frames
    assert all(tl.frame_at(tl.time_of_frame(int(i))) == i for i in f)
    parts = [list(tl.frames_of_segment(m)) for m in range(M)]
    assert sum(parts, []) == list(range(F))
    assert all(tl.segment_of_frame(x) == m for m, p in enumerate(parts) for x in p)


def test_time_is_clamped_and_validated():
    tl = Timeline(11, 3, 3, 2)
    assert tl.frame_at(-0.5) == 0 and tl.frame_at(7.0) == 10
    assert tl.segment_at(1.0) == (1, 1.0)
    assert tl.segment_at(-1) == (0, 0.0)
    with pytest.raises(ValueError, match="NaN"):
        tl.frame_at(float("nan"))
    with pytest.raises(ValueError, match="frame"):
        tl.window_of_frame(11)
    with pytest.raises(ValueError, match="num_keyframes"):
        Timeline(10, 0, 3, 1)


def test_single_frame_and_more_segments_than_frames():
    tl = Timeline(1, 1, 7, 4)
    assert tl.time_of_frame(0) == 0.0 and tl.segment_of_frame(0) == 0 and tl.local_time_of_frame(0) == 0.0
    tl = Timeline(3, 2, 3, 8)  # some segments have no frame
    parts = [list(tl.frames_of_segment(m)) for m in range(8)]
    assert sum(parts, []) == [0, 1, 2]


def _half_up(x: Fraction) -> int:
    return int(x + Fraction(1, 2))  # floor(x + 1/2) for x >= 0


def test_evenly_spaced_against_exact_rationals():
    for n in range(1, 61):
        for k in range(1, n + 3):
            got = evenly_spaced(n, k)
            kk = min(k, n)
            want = [0] if kk == 1 else [_half_up(Fraction(j * (n - 1), kk - 1)) for j in range(kk)]
            assert got == want, (n, k)
            assert len(set(got)) == kk and got == sorted(got) and got[-1] == (n - 1 if kk > 1 else 0)
    assert evenly_spaced(6, 3) == [0, 3, 5]  # the half rounds up (round-half-even gave [0, 2, 5])
    assert evenly_spaced(0, 4) == [] and evenly_spaced(5, 0) == []


def test_prepared_keyframes_agree_with_the_model_for_every_short_sequence():
    """atgs-prepare writes evenly_spaced(F, K) as the scene's keyframes; the model places keyframe
    j at Timeline.keyframe_frame(j). They must agree for every F <= 300 and K <= F."""
    for F in range(1, 301):
        for K in range(1, F + 1):
            assert evenly_spaced(F, K) == Timeline(F, K, 0, 1).keyframe_frames(), (F, K)


def test_module_level_time_helpers_match_the_timeline():
    for F in (1, 2, 7, 300, 10000):
        tl = Timeline(F, min(F, 15), 7, 2)
        for f in {0, F // 3, F // 2, F - 1}:
            assert time_of_frame(f, F) == tl.time_of_frame(f)
            assert frame_at(time_of_frame(f, F), F) == f
        for t in np.linspace(0, 1, 37):
            assert frame_at(float(t), F) == tl.frame_at(float(t))
    assert time_of_frame(12, 10) == 1.0 and time_of_frame(-3, 10) == 0.0  # clamped into the sequence
