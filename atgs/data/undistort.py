"""Removing lens distortion: resample a distorted image onto the pinhole camera with the same K.

The map is computed once per camera (for every output pixel: where it lands in the distorted
image, via the forward OpenCV model) and applied to each frame with a bilinear gather, so
undistorting a long video costs one gather per frame. Pixels that map outside the source are
filled from the nearest border pixel.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from atgs.cameras import Camera, distort_normalized


@dataclass
class UndistortMap:
    camera: Camera  # the undistorted camera (dist=None)
    idx: np.ndarray  # (4, H*W) flat source indices of the 4 bilinear neighbours
    w: np.ndarray  # (4, H*W) float32 weights


def build_undistort_map(cam: Camera) -> UndistortMap:
    if cam.dist is None:
        raise ValueError(f"{cam.name}: camera has no distortion")
    W, H = cam.width, cam.height
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    x, y = (u.ravel() - cam.cx) / cam.fx, (v.ravel() - cam.cy) / cam.fy
    xd, yd = distort_normalized(x, y, cam.dist)
    # continuous source position -> array index space (pixel centers at +0.5)
    sx = np.clip(cam.fx * xd + cam.cx - 0.5, 0.0, W - 1.0)
    sy = np.clip(cam.fy * yd + cam.cy - 0.5, 0.0, H - 1.0)
    x0 = np.minimum(np.floor(sx).astype(np.int64), W - 2 if W > 1 else 0)
    y0 = np.minimum(np.floor(sy).astype(np.int64), H - 2 if H > 1 else 0)
    fx, fy = sx - x0, sy - y0
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    idx = np.stack([y0 * W + x0, y0 * W + x1, y1 * W + x0, y1 * W + x1])
    w = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy]).astype(np.float32)
    return UndistortMap(replace(cam, dist=None), idx, w)


def apply_undistort_map(m: UndistortMap, img: np.ndarray) -> np.ndarray:
    H, W = m.camera.height, m.camera.width
    if img.shape[:2] != (H, W):
        raise ValueError(f"image is {img.shape[1]}x{img.shape[0]}, camera {m.camera.name} is {W}x{H}")
    flat = img.reshape(H * W, -1).astype(np.float32)
    out = sum(flat[m.idx[k]] * m.w[k][:, None] for k in range(4))
    out = out.reshape(H, W, -1)
    if img.dtype == np.uint8:
        return np.clip(np.round(out), 0, 255).astype(np.uint8)
    return out.astype(img.dtype)


def undistort_points_reference(uv: np.ndarray, cam: Camera, iters: int = 50) -> np.ndarray:
    """Slow reference: distorted pixel coordinates -> undistorted ones (fixed-point iteration)."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    xd, yd = (uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy
    x, y = xd.copy(), yd.copy()
    for _ in range(iters):
        ex, ey = distort_normalized(x, y, cam.dist)
        x, y = x - (ex - xd), y - (ey - yd)
    return np.stack([cam.fx * x + cam.cx, cam.fy * y + cam.cy], -1)
