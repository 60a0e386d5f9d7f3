"""The one owner of time and frame-index rules (contract: docs/ARCHITECTURE.md).

Frame f of F sits at t = f / (F - 1). "k evenly spaced indices of n" are round(j (n - 1) / (k - 1))
for j = 0..k-1 with halves rounded up (:func:`evenly_spaced`): the keyframes of a prepared scene
and of the model, the frames sampled by motion measurement, the frames of periodic evaluation and
the comparison images of ``atgs-eval`` all use it, so they agree by construction. All frame-based
mappings use integer arithmetic so that long sequences map exactly; the float path ``*_at(t)``
snaps t to its nearest frame for the discrete choices (window, segment) so that
``gaussians_at(f / (F - 1))`` and ``gaussians_at_frame(f)`` agree.
"""

from __future__ import annotations

from dataclasses import dataclass
import math


def _round_half_up(num: int, den: int) -> int:
    """round(num / den) for integers num >= 0, den > 0, halves rounded up."""
    return (2 * num + den) // (2 * den)


def _round_half_down(num: int, den: int) -> int:
    """round(num / den) for integers, halves rounded down (argmin picks the first index)."""
    return (2 * num + den - 1) // (2 * den)


def evenly_spaced(n: int, k: int) -> list[int]:
    """``min(k, n)`` indices of range(n), evenly spread, first and last included, ascending and
    distinct: index j is round(j (n - 1) / (k - 1)) with halves rounded up (the model's keyframe
    rule, so existing checkpoints keep their keyframes). [] for n <= 0 or k <= 0."""
    n, k = int(n), int(k)
    if n <= 0 or k <= 0:
        return []
    k = min(k, n)
    if k == 1:
        return [0]
    # spacing (n-1)/(k-1) >= 1: rounding never maps two j onto one index
    return [_round_half_up(j * (n - 1), k - 1) for j in range(k)]


def clamp_time(t: float) -> float:
    t = float(t)
    if math.isnan(t):
        raise ValueError("time t is NaN")
    return min(1.0, max(0.0, t))


def time_of_frame(f: int, num_frames: int) -> float:
    """Normalized time of frame f (clamped into the sequence); 0 for a single frame."""
    if num_frames <= 1:
        return 0.0
    return min(max(int(f), 0), num_frames - 1) / (num_frames - 1)


def frame_at(t: float, num_frames: int) -> int:
    """Nearest frame of normalized time t (clamped to [0, 1]); halves round up."""
    return int(math.floor(clamp_time(t) * (num_frames - 1) + 0.5))


@dataclass(frozen=True)
class Timeline:
    num_frames: int  # F >= 1
    num_keyframes: int  # K >= 1
    window: int  # W >= 1, or 0 for "no window"
    num_segments: int  # M >= 1

    def __post_init__(self) -> None:
        if self.num_frames < 1:
            raise ValueError(f"num_frames must be >= 1, got {self.num_frames}")
        if self.num_keyframes < 1:
            raise ValueError(f"num_keyframes must be >= 1, got {self.num_keyframes}")
        if self.window < 0:
            raise ValueError(f"window must be >= 0 (0 = no window), got {self.window}")
        if self.num_segments < 1:
            raise ValueError(f"num_segments must be >= 1, got {self.num_segments}")

    # --- time <-> frame ------------------------------------------------------------
    def time_of_frame(self, f: int) -> float:
        return time_of_frame(self._check_frame(f), self.num_frames)

    def frame_at(self, t: float) -> int:
        """Nearest frame of normalized time t (clamped to [0, 1])."""
        return frame_at(t, self.num_frames)

    def _check_frame(self, f: int) -> int:
        f = int(f)
        if not 0 <= f < self.num_frames:
            raise ValueError(f"frame {f} out of range 0..{self.num_frames - 1}")
        return f

    # --- keyframes -------------------------------------------------------------------
    def keyframe_frame(self, j: int) -> int:
        """Frame index of keyframe j (0-based); K > F repeats frames (the prepared scene's
        :func:`evenly_spaced` caps K at F instead)."""
        K, F = self.num_keyframes, self.num_frames
        if not 0 <= j < K:
            raise ValueError(f"keyframe {j} out of range 0..{K - 1}")
        return 0 if K == 1 else _round_half_up(j * (F - 1), K - 1)

    def keyframe_frames(self) -> list[int]:
        return [self.keyframe_frame(j) for j in range(self.num_keyframes)]

    def nearest_keyframe_of_frame(self, f: int) -> int:
        """0-based kbar = argmin_j |t (K-1) - j| with t = f/(F-1); ties go to the lower j."""
        f = self._check_frame(f)
        K, F = self.num_keyframes, self.num_frames
        if K == 1 or F == 1:
            return 0
        return _round_half_down(f * (K - 1), F - 1)

    def window_of_frame(self, f: int) -> tuple[int, int]:
        """0-based inclusive keyframe window [max(0, kbar-h), min(K-1, kbar+h)]."""
        K = self.num_keyframes
        if self.window == 0:
            return 0, K - 1
        h = self.window // 2
        kbar = self.nearest_keyframe_of_frame(f)
        return max(0, kbar - h), min(K - 1, kbar + h)

    def window_at(self, t: float) -> tuple[int, int]:
        return self.window_of_frame(self.frame_at(t))

    # --- temporal segments ---------------------------------------------------------------
    def segment_of_frame(self, f: int) -> int:
        """m = floor(M t), with t = 1 mapped into the last segment."""
        f = self._check_frame(f)
        F, M = self.num_frames, self.num_segments
        if F == 1:
            return 0
        return min(M - 1, (M * f) // (F - 1))

    def local_time_of_frame(self, f: int) -> float:
        """tau = M t - m in [0, 1]."""
        f = self._check_frame(f)
        F, M = self.num_frames, self.num_segments
        if F == 1:
            return 0.0
        m = self.segment_of_frame(f)
        return (M * f - m * (F - 1)) / (F - 1)

    def segment_at(self, t: float) -> tuple[int, float]:
        """(segment of the nearest frame, local time of t in that segment clamped to [0, 1])."""
        t = clamp_time(t)
        m = self.segment_of_frame(self.frame_at(t))
        return m, min(1.0, max(0.0, self.num_segments * t - m))

    def frames_of_segment(self, m: int) -> range:
        """The contiguous frames whose segment is m (may be empty when M > F - 1)."""
        F, M = self.num_frames, self.num_segments
        if F == 1:
            return range(0, 1) if m == 0 else range(0)
        lo = -((-m * (F - 1)) // M)  # ceil(m (F-1) / M)
        hi = F if m == M - 1 else -((-(m + 1) * (F - 1)) // M)
        return range(min(lo, F), min(hi, F))
