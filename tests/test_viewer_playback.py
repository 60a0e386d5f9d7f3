"""Time -> frame -> keyframe window mapping, playback state, and the decode cache."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import torch

from atgs.gaussians import Gaussians
from atgs.timeline import Timeline, time_of_frame
from atgs.viewer.decode_cache import DecodeCache
from atgs.viewer.packing import PackedGaussians, pack_gaussians
from atgs.viewer.playback import FrameFeeder, Playback
from atgs.viewer.source import GaussianSource, SyntheticSource, decode_frame


def _packed(frame: int) -> PackedGaussians:
    g = Gaussians(torch.full((1, 3), float(frame)), torch.tensor([[1.0, 0, 0, 0]]), torch.ones(1, 3),
                  torch.ones(1), torch.ones(1, 3))
    return pack_gaussians(g, frame=frame)


def test_synthetic_source_window_follows_the_paper_rule() -> None:
    s = SyntheticSource(num_gaussians=10, frames=31, keyframes=7, window=3)
    assert isinstance(s, GaussianSource)
    tl = Timeline(num_frames=31, num_keyframes=7, window=3, num_segments=1)
    for f in range(31):
        t = time_of_frame(f, 31)
        assert s.window_at(t) == tl.window_at(t)
    # by hand: t = 0.5 -> t (K-1) = 3 -> kbar = 3 (0-based), h = 1 -> keyframes 2..4
    assert s.window_at(0.5) == (2, 4)
    assert s.window_at(0.0) == (0, 1) and s.window_at(1.0) == (5, 6)


def test_playback_advance_loop_step_and_seek() -> None:
    p = Playback(num_frames=10, fps=10.0)
    p.advance(1.0)
    assert p.frame == 0  # paused: nothing moves
    p.toggle()
    p.advance(0.25)  # 2.5 frames at 10 fps -> shows frame 3 (round half up)
    assert p.frame == 3 and p.time == pytest.approx(3 / 9)
    p.speed = 2.0
    p.advance(0.3)  # +6 frames -> 8.5 -> frame 9
    assert p.frame == 9
    p.advance(0.05)  # +1 -> wraps to the start
    assert p.frame == 0 and p.playing
    p.loop = False
    p.seek_frame(8)
    p.advance(1.0)
    assert p.frame == 9 and not p.playing  # stops at the end
    p.step(1)
    assert p.frame == 9  # clamped without loop
    p.loop = True
    p.step(1)
    assert p.frame == 0 and not p.playing
    p.step(-1)
    assert p.frame == 9
    p.seek_time(0.5)
    assert p.frame == 5  # round(4.5) half up, same as the model
    assert p.upcoming(4) == [5, 6]  # paused: the frame and its neighbour only
    p.toggle()
    assert p.upcoming(4) == [5, 6, 7, 8]
    p.seek_frame(8)
    assert p.upcoming(4) == [8, 9, 0, 1]


def test_decode_cache_decodes_requested_frames_in_background_lru() -> None:
    calls: list[int] = []

    def decode(f: int) -> PackedGaussians:
        calls.append(f)
        return _packed(f)

    with DecodeCache(decode, capacity=3) as cache:
        cache.request([4, 5, 6])
        assert cache.wait_for(6, timeout=10) is not None
        assert cache.wait_for(4, timeout=10).frame == 4
        assert sorted(cache.cached_frames()) == [4, 5, 6]
        cache.request([7])
        assert cache.wait_for(7, timeout=10) is not None
        assert len(cache.cached_frames()) == 3 and 7 in cache.cached_frames()
        # 5 was least recently used (4 and 6 were read), so it went
        assert 5 not in cache.cached_frames()
        assert calls[:3] == [4, 5, 6]  # priority order of the request
        assert cache.stats.evicted == 1


def test_decode_cache_keeps_decoded_frames_within_the_byte_budget() -> None:
    from atgs.viewer.decode_cache import packed_bytes

    one = packed_bytes(_packed(0))
    assert one == 40 + 4 + 4  # the 40-byte vertex columns (docs/viewer.md) + opacity and extent for the cull
    calls: list[int] = []

    def decode(f: int) -> PackedGaussians:
        calls.append(f)
        return _packed(f)

    # budget for 5 frames, 2 always kept: playing 0..9 in order keeps the last 5
    with DecodeCache(decode, capacity=2, keep_bytes=5 * one) as cache:
        for f in range(10):
            cache.request([f])
            assert cache.wait_for(f, timeout=10) is not None
        assert sorted(cache.cached_frames()) == [5, 6, 7, 8, 9]
        assert cache.cached_bytes == 5 * one and cache.stats.evicted == 5
    # a budget for the whole sequence: a second loop decodes nothing again
    calls.clear()
    with DecodeCache(decode, capacity=2, keep_bytes=100 * one) as cache:
        for loop in range(2):
            for f in range(10):
                cache.request([f])
                assert cache.wait_for(f, timeout=10).frame == f
        assert calls == list(range(10)) and cache.stats.evicted == 0
    # no budget: only `capacity` frames stay
    with DecodeCache(decode, capacity=2) as cache:
        for f in range(6):
            cache.request([f])
            cache.wait_for(f, timeout=10)
        assert sorted(cache.cached_frames()) == [4, 5] and cache.cached_bytes == 2 * one
    with pytest.raises(ValueError, match="keep_bytes"):
        DecodeCache(decode, keep_bytes=-1)


def test_prefetch_fills_the_budget_in_order_and_never_evicts() -> None:
    from atgs.viewer.decode_cache import packed_bytes

    one = packed_bytes(_packed(0))

    def settle(cache: DecodeCache) -> None:  # until the worker has nothing left to do
        assert cache.wait_idle(timeout=10)

    with DecodeCache(_packed, capacity=2, keep_bytes=5 * one) as cache:
        cache.prefetch(range(10))
        settle(cache)
        assert sorted(cache.cached_frames()) == [0, 1, 2, 3, 4] and cache.stats.evicted == 0
        # playback past the budget evicts; from then on prefetching stays off
        for f in (7, 8):
            cache.request([f])
            cache.wait_for(f, timeout=10)
        settle(cache)
        assert cache.stats.evicted == 2 and len(cache.cached_frames()) == 5
        assert cache.stats.decoded == 7
    with DecodeCache(_packed, capacity=2, keep_bytes=100 * one) as cache:
        cache.prefetch([3, 1, 2, 0])
        settle(cache)
        assert list(cache.cached_frames()) == [3, 1, 2, 0]  # decoded in the given order
    with DecodeCache(_packed, capacity=2) as cache:  # no budget: nothing is prefetched
        cache.prefetch(range(10))
        settle(cache)
        assert cache.cached_frames() == [] and cache.stats.decoded == 0


def test_get_never_blocks_and_last_ready_frame_stays() -> None:
    gate = threading.Event()

    def slow_decode(f: int) -> PackedGaussians:
        if f >= 1:
            assert gate.wait(timeout=20)
        return _packed(f)

    with DecodeCache(slow_decode, capacity=4) as cache:
        feeder = FrameFeeder(cache, lookahead=2)
        p = Playback(num_frames=5, fps=10.0)
        cache.wait_for(0, timeout=10)
        shown, changed = feeder.update(p)
        assert shown is not None and shown.frame == 0 and changed
        p.toggle()
        p.advance(0.1)  # now frame 1 is wanted, but its decoder is stuck
        for _ in range(3):  # returns immediately with the old frame every time
            shown, changed = feeder.update(p)
            assert shown.frame == 0 and not changed
        deadline = time.monotonic() + 10
        while cache.busy_frame != 1 and time.monotonic() < deadline:  # the worker picks it up
            time.sleep(0.005)
        assert cache.busy_frame == 1
        assert feeder.update(p)[0].frame == 0  # still the old frame while 1 is being decoded
        gate.set()
        cache.wait_for(1, timeout=10)
        shown, changed = feeder.update(p)
        assert shown.frame == 1 and changed


def test_decode_errors_are_reported_not_fatal() -> None:
    def bad(f: int) -> PackedGaussians:
        if f == 2:
            raise ValueError("boom")
        return _packed(f)

    with DecodeCache(bad, capacity=2) as cache:
        with pytest.raises(RuntimeError, match="frame 2.*boom"):
            cache.wait_for(2, timeout=10)
        assert cache.wait_for(3, timeout=10).frame == 3  # the worker is still alive
        assert "boom" in (cache.last_error or "")


def test_decode_frame_packs_source_gaussians() -> None:
    s = SyntheticSource(num_gaussians=50, frames=5)
    p = decode_frame(s, 2)
    assert p.frame == 2 and len(p) == 50
    g = s.gaussians_at_frame(2)
    np.testing.assert_allclose(p.means, g.means.numpy(), atol=1e-7)


def test_pinned_frames_are_served_without_decoding() -> None:
    calls: list[int] = []

    def decode(f: int) -> PackedGaussians:
        calls.append(f)
        return _packed(f)

    pinned = {f: _packed(f) for f in range(3)}
    with DecodeCache(decode, capacity=2, pinned=pinned) as cache:
        cache.request([0, 1, 2])
        assert cache.get(1) is pinned[1] and cache.wait_for(2) is pinned[2]
        assert cache.wait_for(3, timeout=10).frame == 3
        assert calls == [3]


def test_gil_free_finish_uses_ctypes_gl_or_falls_back(monkeypatch) -> None:
    """The window waits for the splat through a ctypes glFinish (GIL released, so the decode
    thread keeps decoding); without a libglvnd GL library it falls back to the given wait."""
    import ctypes.util

    from atgs.viewer import gl_sync

    calls: list[int] = []

    def fallback() -> None:
        calls.append(1)

    monkeypatch.setattr(gl_sync, "_GL_LIBS", ("libno-such-gl-library.so.0",))
    assert gl_sync.gil_free_finish(fallback) is fallback
    monkeypatch.undo()
    if ctypes.util.find_library("OpenGL") or ctypes.util.find_library("GL"):
        fn = gl_sync.gil_free_finish(fallback)
        assert fn is not fallback and isinstance(fn, ctypes._CFuncPtr)
        assert fn.restype is None and fn.argtypes == []
    assert calls == []
