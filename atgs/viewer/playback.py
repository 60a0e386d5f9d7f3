"""Playback state (time, play/pause, speed, loop, frame step) and the frame feeder that keeps
the last ready frame on screen. Pure Python: no GL, no window."""

from __future__ import annotations

import math
from dataclasses import dataclass

from atgs.timeline import frame_at, time_of_frame
from atgs.viewer.decode_cache import DecodeCache
from atgs.viewer.packing import PackedGaussians


@dataclass
class Playback:
    """Continuous position ``pos`` in frames; frame f is shown for pos in [f - 0.5, f + 0.5)
    so that ``frame == round(t (F - 1))`` matches the model's time -> frame mapping."""

    num_frames: int
    fps: float
    pos: float = 0.0
    playing: bool = False
    speed: float = 1.0
    loop: bool = True

    @property
    def frame(self) -> int:
        return min(self.num_frames - 1, max(0, int(math.floor(self.pos + 0.5))))

    @property
    def time(self) -> float:
        """Normalized time t in [0, 1] of the shown frame."""
        return time_of_frame(self.frame, self.num_frames)

    def seek_time(self, t: float) -> None:
        self.pos = float(frame_at(t, self.num_frames))

    def seek_frame(self, f: int) -> None:
        self.pos = float(min(self.num_frames - 1, max(0, int(f))))

    def step(self, delta: int) -> None:
        """Single-frame step (pauses); wraps around when looping."""
        self.playing = False
        f = self.frame + int(delta)
        if self.loop:
            f %= self.num_frames
        self.seek_frame(f)

    def toggle(self) -> None:
        if not self.playing and not self.loop and self.frame == self.num_frames - 1:
            self.pos = 0.0  # play again from the start
        self.playing = not self.playing

    def advance(self, dt: float) -> None:
        """Move by dt seconds of wall time at ``speed`` x ``fps``."""
        if not self.playing or self.num_frames <= 1:
            return
        self.pos += dt * self.fps * self.speed
        hi = self.num_frames - 0.5
        if self.pos >= hi or self.pos < -0.5:
            if self.loop:
                self.pos = (self.pos + 0.5) % self.num_frames - 0.5
            else:
                self.pos = min(max(self.pos, 0.0), self.num_frames - 1.0)
                self.playing = False

    def upcoming(self, count: int) -> list[int]:
        """The shown frame then the next ``count - 1`` frames in playback direction."""
        f, n = self.frame, self.num_frames
        d = -1 if self.speed < 0 else 1
        out = [f]
        for i in range(1, count if self.playing else min(count, 2)):
            g = f + d * i
            if self.loop:
                g %= n
            elif not 0 <= g < n:
                break
            out.append(g)
        return out


class FrameFeeder:
    """Asks the cache for the wanted frame and what follows; returns the frame to show.

    If the wanted frame is not decoded yet, the newest decoded frame at or behind the playhead
    is shown if it is closer than the one on screen, else the last shown frame stays. So when
    decoding falls behind, playback skips frames instead of freezing, and nothing waits.
    """

    def __init__(self, cache: DecodeCache, lookahead: int = 3) -> None:
        self.cache = cache
        self.lookahead = lookahead
        self.shown: PackedGaussians | None = None

    @staticmethod
    def _behind(playback: Playback, f: int) -> int | None:
        """Frames from f forward to the playhead in playback direction (None: f is ahead)."""
        d = -1 if playback.speed < 0 else 1
        gap = (playback.frame - f) * d
        if playback.loop:
            gap %= playback.num_frames
        return gap if gap >= 0 else None

    def update(self, playback: Playback) -> tuple[PackedGaussians | None, bool]:
        """(frame to show, whether it changed since the last call). Never blocks."""
        self.cache.request(playback.upcoming(self.lookahead + 1))
        p = self.cache.get(playback.frame)
        if p is None:
            best, best_gap = None, None
            for f, q in self.cache.snapshot().items():
                gap = self._behind(playback, f)
                if gap is not None and (best_gap is None or gap < best_gap):
                    best, best_gap = q, gap
            if best is not None and self.shown is not None:
                shown_gap = self._behind(playback, self.shown.frame)
                if shown_gap is not None and shown_gap <= (best_gap or 0):
                    best = None
            if best is None and self.shown is None:
                snap = self.cache.snapshot()
                best = next(iter(snap.values()), None)  # anything beats a blank screen
            p = best
        if p is not None and p is not self.shown:
            self.shown = p
            return p, True
        return self.shown, False

    def after_draw(self, playback: Playback) -> None:
        """Nothing to do: the decode thread works ahead on its own (the GL feeder decodes here)."""

    def close(self) -> None:
        """The cache belongs to the caller."""
