"""A tiny in-memory dynamic scene for tests and smoke runs: a few coloured static Gaussians
and a blob that moves, seen by cameras on a ring. Ground truth is rendered with the
rasterizer itself, so a model can fit it exactly in principle."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from atgs.cameras import Camera, look_at
from atgs.render import rasterize


@dataclass
class ToyScene:
    cameras: list[Camera]
    num_frames: int
    fps: float
    keyframes: list[int]
    points: np.ndarray
    point_keyframes: np.ndarray
    test_cameras: list[str]
    frames: dict = field(default_factory=dict)  # (cam, frame) -> uint8 image

    @property
    def train_indices(self) -> list[int]:
        return [i for i, c in enumerate(self.cameras) if c.name not in self.test_cameras]

    @property
    def test_indices(self) -> list[int]:
        return [i for i, c in enumerate(self.cameras) if c.name in self.test_cameras]

    def image_uint8(self, cam_index: int, frame: int) -> np.ndarray:
        return self.frames[(cam_index, frame)]


def make_toy_scene(num_frames: int = 6, num_cameras: int = 5, width: int = 40, height: int = 32,
                   keyframes: int = 3, seed: int = 0) -> ToyScene:
    gen = torch.Generator().manual_seed(seed)
    n_static = 24
    static = (torch.rand(n_static, 3, generator=gen) - 0.5) * torch.tensor([1.6, 1.6, 0.4])
    static_col = torch.rand(n_static, 3, generator=gen) * 0.8 + 0.1
    cams = []
    for i in range(num_cameras):
        a = 2 * np.pi * i / num_cameras
        eye = np.array([3.0 * np.cos(a), 3.0 * np.sin(a), 1.2])
        f = 0.9 * width
        K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])
        cams.append(Camera(f"cam{i:02d}", width, height, K, look_at(eye, np.zeros(3))))

    def blob(frame: int) -> torch.Tensor:
        s = frame / max(1, num_frames - 1)
        return torch.tensor([[-0.6 + 1.2 * s, 0.0, 0.3]])

    frames = {}
    for fr in range(num_frames):
        means = torch.cat([static, blob(fr)])
        n = means.shape[0]
        quats = torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4).contiguous()
        scales = torch.cat([torch.full((n_static, 3), 0.12), torch.full((1, 3), 0.2)])
        opac = torch.full((n,), 0.9)
        cols = torch.cat([static_col, torch.tensor([[1.0, 0.2, 0.1]])])
        for ci, c in enumerate(cams):
            out = rasterize(means, quats, scales, opac, cols, torch.from_numpy(c.w2c).float(),
                            torch.from_numpy(c.K).float(), width, height, backend="auto")
            frames[(ci, fr)] = (out.image.clamp(0, 1) * 255).round().byte().numpy()
    kf_frames = sorted({round(j * (num_frames - 1) / max(1, keyframes - 1)) for j in range(keyframes)})
    # every keyframe re-observes the static points (with triangulation noise), as real captures do
    pts, pk = [], []
    for j in range(len(kf_frames)):
        pts.append(static + 0.02 * torch.randn(n_static, 3, generator=gen))
        pk.append(torch.full((n_static,), j, dtype=torch.int64))
    for j, fr in enumerate(kf_frames):
        pts.append(blob(fr) + 0.08 * torch.randn(4, 3, generator=gen))
        pk.append(torch.full((4,), j, dtype=torch.int64))
    return ToyScene(cams, num_frames, 30.0, kf_frames, torch.cat(pts).numpy(), torch.cat(pk).numpy(),
                    [cams[-1].name], frames)
