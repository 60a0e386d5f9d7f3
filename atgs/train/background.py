"""The background a run trains and renders over (`--train.background-from-images`).

No Gaussian is ever placed where no training camera looked, so a held-out view shows the
background there. Black, the usual default, is the worst guess for such content. Two better
ones, from the training images:
- the images' mean colour, the least-squares guess when nothing tells one direction from another;
- by direction (`--train.background-by-direction`, an :class:`EnvironmentMap`): for each ray the
  mean colour the training pixels show in about the same direction (a wall above, a floor below),
  so content just beyond what the cameras framed gets the colour of what they framed next to it.
Captures of objects over a uniform backdrop keep that backdrop's colour, so empty space stays
empty.
"""

from __future__ import annotations

from typing import Protocol, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from atgs.cameras import Camera
from atgs.render.environment import EnvironmentMap, map_coordinates, pixel_directions, up_basis
from atgs.timeline import evenly_spaced


class ImageScene(Protocol):
    cameras: list[Camera]
    num_frames: int

    def image_uint8(self, cam_index: int, frame: int) -> np.ndarray: ...


def sample_images(scene: ImageScene, cams: Sequence[int], samples: int = 24) -> list[tuple[int, np.ndarray]]:
    """``max(samples, len(cams))`` (camera, float image) pairs spread over ``cams`` and the sequence."""
    n = max(samples, len(cams))
    frames = evenly_spaced(scene.num_frames, min(n, scene.num_frames))
    out = []
    for i in range(n):
        c = cams[i % len(cams)]
        out.append((c, scene.image_uint8(c, frames[i % len(frames)])[..., :3].astype(np.float32) / 255.0))
    return out


def uniform_backdrop(images: Sequence[np.ndarray], border: int = 2, tolerance: float = 0.04,
                     backdrop_fraction: float = 0.5) -> tuple[float, float, float] | None:
    """The median colour of the images' ``border``-pixel frames if at least ``backdrop_fraction``
    of those pixels lie within ``tolerance`` of it (objects over black or white), else None."""
    edges = []
    for img in images:
        b = max(1, min(border, min(img.shape[:2]) // 2))
        edges += [img[:b].reshape(-1, 3), img[-b:].reshape(-1, 3), img[:, :b].reshape(-1, 3), img[:, -b:].reshape(-1, 3)]
    edge = np.concatenate(edges)
    median = np.median(edge, axis=0)
    if np.mean(np.abs(edge - median).max(axis=1) <= tolerance) >= backdrop_fraction:
        return tuple(float(v) for v in median)
    return None


def resolve_background(scene: ImageScene, cams: Sequence[int], by_direction: bool = True, samples: int = 24
                       ) -> tuple[tuple[float, float, float], EnvironmentMap | None]:
    """What a run trains over, from ``samples`` images of the training cameras ``cams``: a uniform
    backdrop's colour (and no map), else the images' mean colour and, if ``by_direction``, the
    :class:`EnvironmentMap` of :func:`environment_from_images`."""
    if not cams:
        return (0.0, 0.0, 0.0), None
    pairs = sample_images(scene, cams, samples)
    backdrop = uniform_backdrop([img for _, img in pairs])
    if backdrop is not None:
        return backdrop, None
    mean = tuple(float(v) for v in np.mean([img.reshape(-1, 3).mean(axis=0) for _, img in pairs], axis=0))
    return mean, environment_from_images(scene, pairs) if by_direction else None


def _blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of (C, H, W) maps over (elevation, azimuth): circular in azimuth
    (for any kernel width), clamped at the poles."""
    r = max(1, int(3 * sigma))
    k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=torch.float64, device=x.device) / sigma) ** 2)
    c, w = x.shape[0], x.shape[-1]
    m = -(-r // w)  # whole copies of the map needed on each side
    t = torch.cat([x[None].double()] * (2 * m + 1), dim=-1)[..., m * w - r : (m + 1) * w + r]
    t = F.conv2d(t, k.view(1, 1, 1, -1).repeat(c, 1, 1, 1), groups=c)
    t = F.pad(t, (0, 0, r, r), mode="replicate")
    t = F.conv2d(t, k.view(1, 1, -1, 1).repeat(c, 1, 1, 1), groups=c)
    return t[0]


def environment_from_images(scene: ImageScene, pairs: Sequence[tuple[int, np.ndarray]], width: int = 128,
                            blur_deg: float = 12.0, wide_deg: float = 45.0) -> EnvironmentMap:
    """The mean colour the (camera index, float image) ``pairs`` show per direction, on a ``width`` x ``width / 2``
    equirectangular map over the cameras' up axis, blurred over ``blur_deg`` (normalised:
    each texel averages the pixels near its direction). Directions the cameras barely saw blend
    into a ``wide_deg`` blur of the same, and directions none saw at all into the mean colour."""
    height = width // 2
    basis = up_basis([scene.cameras[c] for c, _ in pairs])
    sums = np.zeros((3, height * width))
    counts = np.zeros(height * width)
    for c, img in pairs:
        x, y = map_coordinates(pixel_directions(scene.cameras[c]), basis, width, height)
        idx = (np.clip(y.astype(np.int64), 0, height - 1) * width + x.astype(np.int64) % width).ravel()
        flat = img.reshape(-1, 3).astype(np.float64)
        for ch in range(3):
            sums[ch] += np.bincount(idx, weights=flat[:, ch], minlength=height * width)
        counts += np.bincount(idx, minlength=height * width)
    mean = sums.sum(axis=1) / max(counts.sum(), 1.0)
    s = torch.as_tensor(np.concatenate([sums, counts[None]]).reshape(4, height, width), device="cpu")  # a CPU map
    near = _blur(s, blur_deg / 360.0 * width)
    wide = _blur(s, wide_deg / 360.0 * width)
    eps = 1e-9 * max(counts.sum(), 1.0)
    colour_near = near[:3] / near[3:].clamp_min(eps)
    colour_wide = torch.where(wide[3:] > eps, wide[:3] / wide[3:].clamp_min(eps), torch.as_tensor(mean, device="cpu")[:, None, None])
    # trust the fine map where it holds at least 1% of its densest texel's weight
    w = (near[3:] / (0.01 * near[3].max()).clamp_min(eps)).clamp(0, 1)
    texels = (w * colour_near + (1 - w) * colour_wide).permute(1, 2, 0).float().clamp(0, 1)
    return EnvironmentMap(texels, basis)
