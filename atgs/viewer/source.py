"""What the player plays: anything that gives Gaussians per frame (a trained model, or a
synthetic scene for tests and demos)."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Protocol, runtime_checkable

import numpy as np
import torch

from atgs.cameras import Camera, look_at
from atgs.gaussians import Gaussians
from atgs.timeline import Timeline, frame_at, time_of_frame
from atgs.viewer.packing import PackedGaussians, pack_gaussians
from atgs.viewer.device import cpu_threads


@runtime_checkable
class GaussianSource(Protocol):
    """The subset of the model API (docs/ARCHITECTURE.md) that the viewer uses. A source may also
    have ``near``, the near plane it is drawn with (atgs.model.near_plane.near_of; else 0.01)."""

    @property
    def num_frames(self) -> int: ...

    @property
    def fps(self) -> float: ...

    @property
    def cameras(self) -> list[Camera]: ...

    @property
    def num_keyframes(self) -> int: ...

    def gaussians_at(self, t: float) -> Gaussians: ...

    def gaussians_at_frame(self, f: int) -> Gaussians: ...

    def window_at(self, t: float) -> tuple[int, int]: ...


def active_anchor_count(source: GaussianSource, frame: int) -> int:
    """Number of anchors decoded for a frame, or -1 if the source does not say."""
    fn = getattr(source, "active_anchors", None)
    if fn is None:
        return -1
    try:
        mask = fn(frame)
    except Exception:  # an optional statistic must never break playback
        return -1
    return int(mask.sum()) if hasattr(mask, "sum") else int(mask)


def decode_frame(source: GaussianSource, frame: int, device: torch.device | str | None = None) -> PackedGaussians:
    """Decode and pack one frame (runs in the decode thread). With ``device``, Gaussians decoded
    elsewhere are moved there first, so that packing and sorting run on it (e.g. CUDA).

    A source with view-dependent colour also has ``sh_at_frame(f)``: the frame's (N, K, 3)
    spherical-harmonic coefficients (atgs.sh's order), drawn instead of ``colors``."""
    t0 = time.perf_counter()
    sh_at_frame = getattr(source, "sh_at_frame", None)
    # One torch thread for a CPU decode too (viewer.device.cpu_threads; only this thread's ops).
    with torch.no_grad(), cpu_threads(torch.device("cpu")):
        g = source.gaussians_at_frame(frame)
        sh = None if sh_at_frame is None else sh_at_frame(frame)
        if device is not None and g.means.device != torch.device(device):
            g = g.to(device)
        if sh is not None and device is not None:
            sh = sh.to(device)
    # (packing ends by copying the columns to host memory: decode_ms includes the device's work)
    packed = pack_gaussians(g, frame=frame, num_anchors=active_anchor_count(source, frame), sh=sh)
    packed.decode_ms = (time.perf_counter() - t0) * 1e3
    return packed


def scene_up(cameras: list[Camera]) -> np.ndarray:
    """World direction that is 'up' in the cameras' images on average (OpenCV: -y)."""
    if not cameras:
        return np.array([0.0, 0.0, 1.0])
    ups = np.stack([-c.R[1] for c in cameras])
    u = ups.mean(0)
    n = np.linalg.norm(u)
    return u / n if n > 1e-9 else -cameras[0].R[1]


@dataclass
class SyntheticSource:
    """Moving Gaussians in memory: a ring of colored blobs orbiting the origin and a static
    floor, seen by a ring of cameras. Deterministic for a given seed."""

    num_gaussians: int = 2000
    frames: int = 30
    frame_rate: float = 30.0
    keyframes: int = 4
    window: int = 3
    num_cameras: int = 4
    image_size: tuple[int, int] = (320, 240)
    seed: int = 0
    decode_delay_s: float = 0.0  # simulate a slow decoder (tests of the decode cache)
    device: str = "cpu"  # where gaussians_at_frame returns its tensors (see to())

    def __post_init__(self) -> None:
        rng = np.random.default_rng(self.seed)
        n = self.num_gaussians
        n_floor = n // 4
        n_ring = n - n_floor
        ang = rng.uniform(0, 2 * np.pi, n_ring)
        rad = rng.uniform(0.5, 1.0, n_ring)
        self._ring = np.stack([rad * np.cos(ang), rad * np.sin(ang), rng.uniform(-0.3, 0.3, n_ring)], 1)
        floor = np.stack([rng.uniform(-1.5, 1.5, n_floor), rng.uniform(-1.5, 1.5, n_floor), np.full(n_floor, -0.5)], 1)
        self._floor = floor
        self._quats = rng.normal(size=(n, 4))
        base = 0.6 / max(1.0, n ** (1 / 3))
        self._scales = base * rng.uniform(0.5, 1.5, (n, 3))
        self._scales[n_ring:, 2] *= 0.2
        self._opac = rng.uniform(0.5, 1.0, n)
        hue = np.concatenate([ang / (2 * np.pi), np.full(n_floor, 0.1)])
        self._colors = np.stack(
            [0.5 + 0.5 * np.cos(2 * np.pi * (hue + k / 3)) for k in range(3)], 1
        ) * np.concatenate([np.ones(n_ring), np.full(n_floor, 0.6)])[:, None]
        W, H = self.image_size
        f = 0.9 * W
        K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
        cams = []
        for i in range(self.num_cameras):
            a = 2 * np.pi * i / self.num_cameras
            eye = np.array([3.5 * np.cos(a), 3.5 * np.sin(a), 1.2])
            cams.append(Camera(f"cam{i:02d}", W, H, K, look_at(eye, np.zeros(3), np.array([0, 0, 1.0]))))
        self._cameras = cams
        # Per-frame decode copies these float32 arrays with numpy: torch's float64 -> float32
        # conversions (and even its clone) took ~30 ms of a 20k-Gaussian frame on this 2-core
        # machine, competing with the draw; numpy copies take ~0.1 ms.
        self._static = tuple(
            np.ascontiguousarray(a, dtype=np.float32) for a in (self._quats, self._scales, self._opac, self._colors)
        )

    @property
    def num_frames(self) -> int:
        return self.frames

    @property
    def fps(self) -> float:
        return self.frame_rate

    @property
    def cameras(self) -> list[Camera]:
        return self._cameras

    @property
    def num_keyframes(self) -> int:
        return self.keyframes

    def window_at(self, t: float) -> tuple[int, int]:
        return Timeline(self.frames, self.keyframes, self.window, 1).window_at(t)

    def gaussians_at(self, t: float) -> Gaussians:
        return self.gaussians_at_frame(frame_at(t, self.frames))

    def gaussians_at_frame(self, f: int) -> Gaussians:
        if not 0 <= f < self.frames:
            raise ValueError(f"frame {f} out of range 0..{self.frames - 1}")
        if self.decode_delay_s:
            time.sleep(self.decode_delay_s)
        t = time_of_frame(f, self.frames)
        a = 2 * np.pi * t
        c, s = np.cos(a), np.sin(a)
        ring = self._ring @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1.0]])
        means = np.concatenate([ring, self._floor]).astype(np.float32)
        quats, scales, opac, colors = (torch.from_numpy(a.copy()) for a in self._static)  # callers may modify them
        g = Gaussians(means=torch.from_numpy(means), quats=quats, scales=scales, opacities=opac, colors=colors)
        return g if self.device == "cpu" else g.to(self.device)

    def to(self, device: torch.device | str) -> "SyntheticSource":
        """The same scene decoding onto ``device``."""
        return replace(self, device=str(torch.device(device)))
