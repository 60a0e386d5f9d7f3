"""Projection into a camera's image: the one test "in front of the camera and inside its image".

:func:`project` takes numpy points (float64, through :meth:`Camera.project`, distortion
included) or torch tensors (the pinhole of :func:`atgs.cameras.pinhole_pixels`, in the tensor's
dtype and device, for the undistorted cameras of a prepared scene) and returns pixel
coordinates, depths and the mask of the points in front of ``near`` and inside the image.

The users differ in what "in front" means, so ``near`` is a parameter, not a choice made here:
0 (strictly in front: free space, the per-ray depths, the stereo's views) or 1e-9 (coverage and
the surface extension, which divide by the depth). :func:`in_image` alone is the test of a user
whose depth test is its own (the seen space's near/far range).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from atgs.cameras import Camera, pinhole_pixels, to_camera_frame


class Projected(NamedTuple):
    """Pixel coordinates ``u``, ``v`` (pixel centres at i + 0.5), depth ``z`` (each (N,)), and
    ``inside``: (N,) bool, in front of the near plane and inside the image."""

    u: np.ndarray | torch.Tensor
    v: np.ndarray | torch.Tensor
    z: np.ndarray | torch.Tensor
    inside: np.ndarray | torch.Tensor


def in_image(cam: Camera, u: np.ndarray | torch.Tensor, v: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
    """(N,) bool: pixel coordinates inside ``cam``'s image (NaN: outside)."""
    with np.errstate(invalid="ignore"):
        return (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)


def project(cam: Camera, points: np.ndarray | torch.Tensor, near: float = 0.0) -> Projected:
    """World points (N, 3) -> :class:`Projected` (u, v, z, in front of ``near`` and inside the
    image). numpy points go through :meth:`Camera.project` (float64, with distortion); a torch
    tensor through the pinhole in its own dtype and device, its depth clamped to 1e-9 before
    dividing (the mask leaves out whatever that clamp touches, for ``near`` >= 0)."""
    if isinstance(points, torch.Tensor):
        pc = to_camera_frame(cam, points)
        z = pc[:, 2]
        u, v = pinhole_pixels(cam, pc, z.clamp_min(1e-9))
    else:
        uv, z = cam.project(np.asarray(points, np.float64).reshape(-1, 3))
        u, v = uv[:, 0], uv[:, 1]
    with np.errstate(invalid="ignore"):
        inside = (z > near) & in_image(cam, u, v)
    return Projected(u, v, z, inside)
