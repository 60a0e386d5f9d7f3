"""What the player's camera-path panel edits: the keyframe list, its timing and the preview
clock. Pure Python (no GL, no imgui), so every edit is unit-testable.

Keyframes stay in video order (``video_t`` strictly increasing with the list index). With
``even_timing`` (the default) they are spread evenly over the video after every edit; without
it each keyframe keeps its own ``video_t`` and edits preserve the timing of the others.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from atgs.viewer.camera_path import CameraPath, PathKey, frame_position


@dataclass
class PathEditor:
    path: CameraPath = field(default_factory=CameraPath)
    selected: int | None = None
    even_timing: bool = True
    previewing: bool = False
    clock_s: float = 0.0  # preview time since its start, seconds of video
    frame: int = 0  # the video frame the view shows while previewing or scrubbing
    revision: int = 0  # bumped by every edit (caches of the drawn path compare it)
    _fresh: bool = False  # the preview started this UI frame: frame 0 is shown for a whole frame

    @property
    def keys(self) -> list[PathKey]:
        return self.path.keys

    @property
    def num_frames(self) -> int:
        return self.path.frame_count()

    def replace_path(self, path: CameraPath) -> None:
        """A loaded path; even timing stays on only if its keyframes are evenly spread."""
        self.path = path
        n = len(path.keys)
        self.even_timing = all(abs(k.video_t - frame_position(i, n)) < 1e-9 for i, k in enumerate(path.keys))
        self.selected = 0 if n else None
        self.stop_preview()
        self._edited()

    # --- keyframe edits ----------------------------------------------------------------------
    def add(self, key: PathKey) -> int:
        """Insert after the selected keyframe (at the end if none); returns its index, selected."""
        keys = self.keys
        k = len(keys)
        j = k if self.selected is None else self.selected + 1
        key = key.copy()
        if not self.even_timing:
            if j < k:  # between two keyframes: halfway
                key.video_t = 0.5 * (keys[j - 1].video_t + keys[j].video_t)
            elif k == 0:
                key.video_t = 0.0
            elif keys[-1].video_t < 1.0:
                key.video_t = 1.0
            else:  # the path already ends at 1: squeeze it so the new last segment gets an average share
                t0 = 0.0 if k == 1 else keys[0].video_t
                for old in keys:
                    old.video_t = t0 + (old.video_t - t0) * (k - 1) / k
                key.video_t = 1.0
        keys.insert(j, key)
        self.selected = j
        self._edited()
        return j

    def update(self, i: int, key: PathKey) -> None:
        """New pose, field of view and scene time for keyframe i (its place in the video stays)."""
        new = key.copy()
        new.video_t = self.keys[i].video_t
        self.keys[i] = new
        self._edited()

    def delete(self, i: int) -> None:
        del self.keys[i]
        n = len(self.keys)
        self.selected = None if n == 0 else min(i, n - 1)
        self._edited()

    def move(self, i: int, delta: int) -> int:
        """Swap keyframe i with its neighbour (delta = -1 earlier, +1 later); the time slots stay."""
        j = i + delta
        if not (0 <= i < len(self.keys) and 0 <= j < len(self.keys)):
            return i
        a, b = self.keys[i], self.keys[j]
        a.video_t, b.video_t = b.video_t, a.video_t
        self.keys[i], self.keys[j] = b, a
        self.selected = j
        self._edited()
        return j

    def set_video_t(self, i: int, video_t: float) -> None:
        """Manual timing: move keyframe i in the video, strictly between its neighbours."""
        keys, gap = self.keys, 1e-4
        lo = keys[i - 1].video_t + gap if i > 0 else 0.0
        hi = keys[i + 1].video_t - gap if i + 1 < len(keys) else 1.0
        keys[i].video_t = min(hi, max(lo, float(video_t)))
        self._edited()

    def set_scene_t(self, i: int, scene_t: float) -> None:
        self.keys[i].scene_t = min(1.0, max(0.0, float(scene_t)))
        self._edited()

    def spread_scene_time(self) -> None:
        """Scene time runs through the whole sequence along the path (scene_t = video_t)."""
        for k in self.keys:
            k.scene_t = k.video_t
        self._edited()

    def set_timing(self, duration_s: float | None = None, fps: float | None = None) -> None:
        """Video length and frame rate (both > 0; others are ignored)."""
        if duration_s is not None and duration_s > 0:
            self.path.duration_s = float(duration_s)
        if fps is not None and fps > 0:
            self.path.fps = float(fps)
        self._edited()

    def set_even_timing(self, on: bool) -> None:
        self.even_timing = bool(on)
        self._edited()

    def _edited(self) -> None:
        if self.even_timing:
            n = len(self.keys)
            for i, k in enumerate(self.keys):
                k.video_t = frame_position(i, n)
        self.frame = min(self.frame, self.num_frames - 1)
        self.revision += 1

    # --- preview -----------------------------------------------------------------------------
    def start_preview(self) -> None:
        if self.keys:
            self.previewing, self.clock_s, self.frame, self._fresh = True, 0.0, 0, True

    def stop_preview(self) -> None:
        self.previewing = False

    def seek(self, frame: int) -> None:
        """Scrub along the path (stops a running preview)."""
        self.previewing = False
        self.frame = min(max(0, int(frame)), self.num_frames - 1)

    def advance(self, dt: float) -> None:
        """Preview clock: frame i of the video is shown from i / fps to (i + 1) / fps seconds,
        like a player would; after the last frame the preview stops there."""
        if not self.previewing:
            return
        if self._fresh:  # started during this UI frame: its first frame has not been on screen yet
            self._fresh = False
            return
        self.clock_s += max(0.0, dt)
        n = self.num_frames
        i = int(math.floor(self.clock_s * self.path.fps + 1e-9))
        if i >= n:
            self.previewing, i = False, n - 1
        self.frame = i

    @property
    def video_t(self) -> float:
        return frame_position(self.frame, self.num_frames)
