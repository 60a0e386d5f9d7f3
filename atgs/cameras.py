"""The one camera type of ATGS.

Convention (used everywhere: data, training rasterizer, viewer):
- pinhole intrinsics ``K`` (3x3), pixel centers at (x + 0.5, y + 0.5);
- ``w2c`` is a 4x4 world-to-camera matrix in OpenCV axes (x right, y down, z forward);
- ``dist`` holds OpenCV distortion coefficients (k1, k2, p1, p2[, k3]) or ``None``.
  Prepared scenes are always undistorted, so cameras in a prepared scene have ``dist=None``.

Conversions to and from dataset formats live in :mod:`atgs.data.camera_formats`.
:meth:`Camera.project` projects numpy points (float64, with distortion); :func:`to_camera_frame`,
:func:`pinhole_pixels` and :func:`pinhole_jacobian` are the same pinhole in torch, in the
points' dtype and device, for the prepared scene's undistorted cameras.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch

# OpenCV camera axes -> OpenGL camera axes (y up, z backward).
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class Camera:
    name: str
    width: int
    height: int
    K: np.ndarray
    w2c: np.ndarray
    dist: np.ndarray | None = field(default=None)

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        self.w2c = np.asarray(self.w2c, dtype=np.float64).reshape(4, 4)
        if self.dist is not None:
            self.dist = np.asarray(self.dist, dtype=np.float64).reshape(-1)
            if not np.any(self.dist):
                self.dist = None
        self.width, self.height = int(self.width), int(self.height)

    # --- geometry -------------------------------------------------------------------
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def R(self) -> np.ndarray:
        return self.w2c[:3, :3]

    @property
    def t(self) -> np.ndarray:
        return self.w2c[:3, 3]

    @property
    def c2w(self) -> np.ndarray:
        return np.linalg.inv(self.w2c)

    @property
    def center(self) -> np.ndarray:
        """Camera center in world coordinates."""
        return -self.R.T @ self.t

    @property
    def forward(self) -> np.ndarray:
        """Viewing direction (camera +z) in world coordinates."""
        return self.R[2].copy()

    def fov_y(self) -> float:
        return 2.0 * float(np.arctan(0.5 * self.height / self.fy))

    def fov_x(self) -> float:
        return 2.0 * float(np.arctan(0.5 * self.width / self.fx))

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (N,3) -> pixel coordinates (N,2) and view depth (N,).

        Pixel coordinates are continuous: the center of pixel (i, j) is (i + 0.5, j + 0.5).
        Distortion, if any, is applied with the OpenCV model.
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        pc = p @ self.R.T + self.t
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = pc[:, 0] / z, pc[:, 1] / z
        if self.dist is not None:
            x, y = distort_normalized(x, y, self.dist)
        uv = np.stack([self.fx * x + self.cx, self.fy * y + self.cy], axis=-1)
        return uv, z

    # --- derived cameras ----------------------------------------------------------------
    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by ``factor`` (e.g. 0.5 for 2x downscale).

        Pixel-center convention: u' = factor * u, so principal points scale too.
        """
        w, h = max(1, int(round(self.width * factor))), max(1, int(round(self.height * factor)))
        sx, sy = w / self.width, h / self.height
        K = self.K.copy()
        K[0] *= sx
        K[1] *= sy
        return replace(self, width=w, height=h, K=K)

    # --- OpenGL ---------------------------------------------------------------------------
    def gl_view(self) -> np.ndarray:
        """4x4 OpenGL view matrix (camera looks down -z, y up)."""
        return CV_TO_GL @ self.w2c

    def gl_projection(self, near: float = 0.01, far: float = 1000.0) -> np.ndarray:
        """4x4 OpenGL projection matching ``K`` exactly (including an off-center principal point).

        A point that projects to pixel (u, v) with OpenCV conventions lands at
        NDC x = 2u/W - 1, y = 1 - 2v/H (OpenGL's y points up).
        """
        W, H = self.width, self.height
        P = np.zeros((4, 4))
        P[0, 0] = 2.0 * self.fx / W
        P[0, 2] = 1.0 - 2.0 * self.cx / W
        P[1, 1] = 2.0 * self.fy / H
        P[1, 2] = 2.0 * self.cy / H - 1.0
        P[2, 2] = -(far + near) / (far - near)
        P[2, 3] = -2.0 * far * near / (far - near)
        P[3, 2] = -1.0
        return P

    # --- serialisation ----------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "w2c": self.w2c.tolist(),
            "dist": None if self.dist is None else self.dist.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "Camera":
        return cls(
            name=str(d["name"]),
            width=int(d["width"]),
            height=int(d["height"]),
            K=np.asarray(d["K"], dtype=np.float64),
            w2c=np.asarray(d["w2c"], dtype=np.float64),
            dist=None if d.get("dist") is None else np.asarray(d["dist"], dtype=np.float64),
        )


def to_camera_frame(cam: Camera, x: torch.Tensor) -> torch.Tensor:
    """World points (N, 3) -> the same points in ``cam``'s OpenCV camera frame (z = depth), in
    x's dtype and device."""
    R = torch.as_tensor(cam.R, dtype=x.dtype, device=x.device)
    t = torch.as_tensor(cam.t, dtype=x.dtype, device=x.device)
    return x @ R.T + t


def pinhole_pixels(cam: Camera, pc: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel coordinates (u, v), each (N,), of camera-frame points ``pc`` (N, 3) seen at depths
    ``z`` (N,): ``pc``'s z made safe to divide by, each caller its own way (clamped, or 1 behind
    the camera). The distortion ``cam.dist`` is not applied: the cameras of a prepared scene
    are undistorted."""
    return cam.fx * pc[..., 0] / z + cam.cx, cam.fy * pc[..., 1] / z + cam.cy


def pinhole_jacobian(cam: Camera, pc: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """(N, 2, 3) derivative of :func:`pinhole_pixels` (u, v) with respect to the world point,
    at camera-frame points ``pc`` (N, 3) seen at depths ``z`` (N,)."""
    j = torch.zeros(pc.shape[0], 2, 3, dtype=pc.dtype, device=pc.device)  # d(u, v)/d(camera point)
    j[:, 0, 0] = cam.fx / z
    j[:, 0, 2] = -cam.fx * pc[:, 0] / z**2
    j[:, 1, 1] = cam.fy / z
    j[:, 1, 2] = -cam.fy * pc[:, 1] / z**2
    return j @ torch.as_tensor(cam.R, dtype=pc.dtype, device=pc.device)  # then through the rotation


def distort_normalized(x: np.ndarray, y: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV radial-tangential distortion of normalized image coordinates."""
    d = np.zeros(5)
    d[: min(5, len(dist))] = dist[:5]
    k1, k2, p1, p2, k3 = d
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """OpenCV world-to-camera matrix of a camera at ``eye`` looking at ``target``.

    ``up`` is the world direction that appears upward in the image.
    """
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)  # OpenCV: y (image down) = -up, and x = y cross z = z cross up
    if np.linalg.norm(x) < 1e-9:  # looking along up: pick any perpendicular
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    return w2c
