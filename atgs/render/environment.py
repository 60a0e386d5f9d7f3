"""A background that depends on the viewing direction: an equirectangular colour map.

Where no Gaussian covers a pixel, a view shows the background. A single colour is the best
guess only if nothing tells one direction from another; an environment map gives each ray the
colour seen in its direction (a wall above, a floor below, the sky), which is what a held-out
view most likely shows where no training camera looked. ``atgs/train/background.py`` builds one
from the training images; the renderers composite it as ``C + T * env(direction)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from atgs.cameras import Camera


def pixel_directions(cam: Camera) -> np.ndarray:
    """(H, W, 3) unit world directions of the rays through the pixel centres of ``cam``
    (lens distortion ignored: a background varies slowly with direction)."""
    v, u = np.mgrid[0 : cam.height, 0 : cam.width]
    x = (u + 0.5 - cam.cx) / cam.fx
    y = (v + 0.5 - cam.cy) / cam.fy
    d = np.stack([x, y, np.ones_like(x)], axis=-1) @ cam.R  # camera -> world: R^T d
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def up_basis(cameras: list[Camera]) -> np.ndarray:
    """(3, 3) rotation from world to a frame whose z axis is the cameras' mean image-up
    direction (so that the map's rows are elevations of the capture, whatever its world axes)."""
    up = np.mean([-c.R[1] for c in cameras], axis=0) if cameras else np.zeros(3)
    if np.linalg.norm(up) < 1e-6:
        up = np.array([0.0, 0.0, 1.0])
    up = up / np.linalg.norm(up)
    a = np.cross(up, [1.0, 0.0, 0.0])
    if np.linalg.norm(a) < 0.1:
        a = np.cross(up, [0.0, 1.0, 0.0])
    a = a / np.linalg.norm(a)
    return np.stack([a, np.cross(up, a), up])


def map_coordinates(directions: np.ndarray, basis: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Continuous texel coordinates (x in [0, width) wrapping, y in [0, height)) of unit world
    ``directions`` (..., 3): x from the azimuth, y from the elevation, texel centres at +0.5."""
    d = directions @ basis.T
    az = np.arctan2(d[..., 1], d[..., 0])
    el = np.arcsin(np.clip(d[..., 2], -1.0, 1.0))
    return (az + math.pi) / (2 * math.pi) * width, (el + math.pi / 2) / math.pi * height


@dataclass
class EnvironmentMap:
    """``texels`` (H, W, 3) colours over (elevation, azimuth) of the frame ``basis`` (3, 3,
    world -> map frame, z up)."""

    texels: torch.Tensor
    basis: np.ndarray
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.texels = torch.as_tensor(self.texels, dtype=torch.float32).detach().cpu()
        self.basis = np.asarray(self.basis, dtype=np.float64).reshape(3, 3)
        if self.texels.ndim != 3 or self.texels.shape[-1] != 3 or min(self.texels.shape[:2]) < 1:
            raise ValueError(f"environment texels must be (H, W, 3), got {tuple(self.texels.shape)}")

    def lookup(self, directions: np.ndarray) -> torch.Tensor:
        """(..., 3) colours of unit world ``directions`` (..., 3), bilinear, wrapping in azimuth."""
        h, w = self.texels.shape[:2]
        x, y = map_coordinates(np.asarray(directions, dtype=np.float64), self.basis, w, h)
        x, y = x - 0.5, np.clip(y - 0.5, 0.0, h - 1.0)
        x0, y0 = np.floor(x), np.floor(y)
        fx = torch.as_tensor(x - x0, dtype=torch.float32)[..., None]
        fy = torch.as_tensor(y - y0, dtype=torch.float32)[..., None]
        x0, y0 = x0.astype(np.int64) % w, y0.astype(np.int64)
        x1, y1 = (x0 + 1) % w, np.minimum(y0 + 1, h - 1)
        t = self.texels
        top = t[y0, x0] * (1 - fx) + t[y0, x1] * fx
        bottom = t[y1, x0] * (1 - fx) + t[y1, x1] * fx
        return top * (1 - fy) + bottom * fy

    def image(self, cam: Camera, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """(H, W, 3) background of ``cam``'s pixels (cached per camera)."""
        key = (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, cam.R.tobytes(), str(device), dtype)
        img = self._cache.get(key)
        if img is None:
            if len(self._cache) > 64:
                self._cache.clear()
            img = self.lookup(pixel_directions(cam)).to(device=device, dtype=dtype)
            self._cache[key] = img
        return img

    def mean_colour(self) -> tuple[float, float, float]:
        return tuple(float(v) for v in self.texels.reshape(-1, 3).mean(0))

    def to_state(self) -> dict:
        return {"texels": self.texels.clone(), "basis": self.basis.tolist()}

    @classmethod
    def from_state(cls, state: dict) -> "EnvironmentMap":
        return cls(torch.as_tensor(state["texels"]), np.asarray(state["basis"], dtype=np.float64))
