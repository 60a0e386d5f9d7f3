"""The space the training cameras' own housings take up: no Gaussian may sit there.

On a ring or a dome every camera sees the others, so training fits Gaussians to the other
cameras' bodies. A camera's body sits around its own lens, where that camera never sees it, and
the space just in front of a training camera is where floaters that explain only that camera's
image would grow.

The clearance is a ball around every *training* camera whose radius is a small fraction of the
distance from the training cameras to the scene: a camera's housing, not scene content. Both
decodes (training and the cached inference decode of the player, evaluation and export) drop the
Gaussians inside, so what training optimises is what every view shows.

A held-out camera gets no ball, and its position sets no radius: nothing about a held-out camera
enters training (issue 49). Its housing, which the training cameras see, stays in front of its
lens, and its held-out score pays for that. (Until issue 49 the balls were around every camera,
held-out ones included: the 20.95 -> 28.26 dB once quoted here for a 10-camera ring came from
the held-out camera's own ball, that is from its pose; docs/model.md, "Camera clearance".)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from atgs.cameras import Camera

DEFAULT_FRACTION = 0.02
"""Ball radius as a fraction of the median camera-to-scene distance (ModelConfig.camera_clearance)."""


def clearance_radius(cameras: Sequence[Camera], scene_centre: np.ndarray, fraction: float) -> float:
    """``fraction`` of the median distance from the cameras' centres (the training cameras') to
    ``scene_centre`` (0 for no cameras or a fraction of 0)."""
    if fraction <= 0 or not cameras:
        return 0.0
    centres = np.stack([c.center for c in cameras])
    return float(fraction * np.median(np.linalg.norm(centres - np.asarray(scene_centre)[None], axis=1)))


@dataclass
class CameraClearance:
    """Balls of ``radius`` around ``centres`` (C, 3: the training cameras'); radius 0 keeps everything."""

    centres: torch.Tensor
    radius: float

    @classmethod
    def of_cameras(cls, cameras: Sequence[Camera], radius: float, device: torch.device | str = "cpu") -> "CameraClearance":
        centres = np.stack([c.center for c in cameras]) if cameras else np.zeros((0, 3))
        return cls(torch.as_tensor(centres, dtype=torch.float32, device=device), float(radius))

    @property
    def active(self) -> bool:
        return self.radius > 0 and self.centres.shape[0] > 0

    def to(self, device: torch.device | str) -> "CameraClearance":
        return CameraClearance(self.centres.to(device), self.radius)

    def outside(self, means: torch.Tensor) -> torch.Tensor:
        """(N,) bool: True where a mean lies outside every ball (all True when inactive)."""
        if not self.active or means.shape[0] == 0:
            return torch.ones(means.shape[0], dtype=torch.bool, device=means.device)
        c = self.centres.to(means.device, means.dtype)
        # (N, C) squared distances in chunks of the cameras would only matter for hundreds of
        # cameras; rigs have at most ~100, so N x C stays a few MB per million Gaussians per camera.
        near = torch.zeros(means.shape[0], dtype=torch.bool, device=means.device)
        r2 = self.radius ** 2
        for start in range(0, c.shape[0], 16):
            d2 = torch.cdist(means, c[start:start + 16]).square()
            near |= (d2 < r2).any(dim=1)
        return ~near
