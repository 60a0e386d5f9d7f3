"""3D Gaussian splatting PLY files as a player source: one file (a static scene of one frame)
or a folder of per-frame files (a sequence), read by atgs.io.gaussian_ply.

Frames are read from disk when the decode thread asks for them (the player's decode cache keeps
the packed frames); the spherical-harmonic coefficients go to the shader through
``sh_at_frame`` (viewer.source.decode_frame), so view-dependent colour of degree 1-3 is drawn."""

from __future__ import annotations

import threading
from pathlib import Path

import torch

from atgs.cameras import Camera
from atgs.gaussians import Gaussians
from atgs.io.gaussian_ply import GaussianPly, read_gaussian_ply
from atgs.io.ply_sequence import PlySequence, open_ply_sequence
from atgs.render.constants import NEAR
from atgs.timeline import frame_at


class PlySource:
    """A GaussianSource over a :class:`~atgs.io.ply_sequence.PlySequence`: frame i is the i-th
    file in frame-number order. A PLY sequence has no keyframes (``num_keyframes`` 0)."""

    def __init__(self, sequence: PlySequence) -> None:
        self.sequence = sequence
        self._lock = threading.Lock()
        self._last: tuple[int, GaussianPly] | None = None  # decode_frame asks for Gaussians, then SH

    @classmethod
    def open(cls, path: str | Path, fps: float | None = None) -> "PlySource":
        return cls(open_ply_sequence(path, fps))

    @property
    def num_frames(self) -> int:
        return len(self.sequence.files)

    @property
    def fps(self) -> float:
        return self.sequence.fps

    @property
    def cameras(self) -> list[Camera]:
        return self.sequence.cameras

    @property
    def num_keyframes(self) -> int:
        return 0

    @property
    def near(self) -> float:
        """The near plane to draw with: the exporting model's (manifest.json), else 0.01."""
        man = self.sequence.manifest
        return float(man["near"]) if man is not None else NEAR

    def window_at(self, t: float) -> tuple[int, int]:
        return (0, -1)  # no keyframe window

    def frame_file(self, f: int) -> Path:
        if not 0 <= f < self.num_frames:
            raise ValueError(f"frame {f} out of range 0..{self.num_frames - 1}")
        return self.sequence.files[f]

    def read_frame(self, f: int) -> GaussianPly:
        with self._lock:
            if self._last is None or self._last[0] != f:
                self._last = (f, read_gaussian_ply(self.frame_file(f)))
            return self._last[1]

    def gaussians_at(self, t: float) -> Gaussians:
        return self.gaussians_at_frame(frame_at(t, self.num_frames))

    def gaussians_at_frame(self, f: int) -> Gaussians:
        return self.read_frame(f).gaussians.map(torch.clone)  # callers may modify what they get

    def sh_at_frame(self, f: int) -> torch.Tensor:
        """(N, K, 3) SH coefficients of frame f (atgs.sh's order)."""
        return self.read_frame(f).sh.clone()
