"""Free camera for the player: orbit / pan / zoom around a pivot, fly (WASD/QE + mouse look),
snap to training cameras, field of view, reset. Pure math on OpenCV cameras (no GL)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from atgs.cameras import Camera
from atgs.rotations import axis_angle_matrix

MIN_POLAR = math.radians(2.0)  # orbit/look stop short of the poles (no flip over the up axis)
MIN_DISTANCE = 1e-4


def intrinsics(width: int, height: int, fov_y: float) -> np.ndarray:
    """Square-pixel K with the principal point at the image center."""
    f = 0.5 * height / math.tan(0.5 * fov_y)
    return np.array([[f, 0.0, 0.5 * width], [0.0, f, 0.5 * height], [0.0, 0.0, 1.0]])


@dataclass
class ViewState:
    eye: np.ndarray  # camera center (world)
    R: np.ndarray  # world-to-camera rotation, rows = right, down, forward (OpenCV)
    distance: float  # pivot = eye + distance * forward
    fov_y: float  # radians

    def copy(self) -> "ViewState":
        return ViewState(self.eye.copy(), self.R.copy(), float(self.distance), float(self.fov_y))


@dataclass
class CameraControl:
    """Camera state plus the world up direction; ``home`` is what :meth:`reset` returns to."""

    state: ViewState
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    home: ViewState | None = None

    def __post_init__(self) -> None:
        self.up = np.asarray(self.up, dtype=np.float64) / np.linalg.norm(self.up)
        if self.home is None:
            self.home = self.state.copy()

    # --- construction / conversion ----------------------------------------------------------
    @classmethod
    def from_camera(cls, cam: Camera, pivot: np.ndarray | None = None, up: np.ndarray | None = None) -> "CameraControl":
        """Start at a training camera; the pivot is ``pivot`` projected on the viewing axis."""
        st = _state_of(cam, pivot)
        return cls(state=st, up=np.array([0.0, 0.0, 1.0]) if up is None else up)

    def camera(self, width: int, height: int, name: str = "view") -> Camera:
        s = self.state
        w2c = np.eye(4)
        w2c[:3, :3] = s.R
        w2c[:3, 3] = -s.R @ s.eye
        return Camera(name, width, height, intrinsics(width, height, s.fov_y), w2c)

    @property
    def forward(self) -> np.ndarray:
        return self.state.R[2].copy()

    @property
    def right(self) -> np.ndarray:
        return self.state.R[0].copy()

    @property
    def down(self) -> np.ndarray:
        return self.state.R[1].copy()

    @property
    def pivot(self) -> np.ndarray:
        return self.state.eye + self.state.distance * self.state.R[2]

    # --- operations ------------------------------------------------------------------------
    def _rotate(self, Q: np.ndarray, about: np.ndarray) -> None:
        s = self.state
        s.eye = about + Q @ (s.eye - about)
        s.R = _orthonormalize(s.R @ Q.T)  # c2w' = Q c2w  <=>  w2c' = w2c Q^T

    def _clamped_pitch(self, dpitch: float) -> float:
        """Limit pitch so the forward axis stays MIN_POLAR away from +-up."""
        polar = math.acos(float(np.clip(self.forward @ self.up, -1.0, 1.0)))  # 0 = looking straight up
        # Positive pitch tilts the view up (toward +up): polar decreases.
        return float(np.clip(dpitch, polar - (math.pi - MIN_POLAR), polar - MIN_POLAR))

    def orbit(self, dyaw: float, dpitch: float) -> None:
        """Rotate the camera around the pivot: yaw about the world up axis, then pitch about the
        camera's right axis (positive pitch raises the camera's view direction). The pivot stays
        at the image center and the distance is unchanged."""
        p = self.pivot
        self._rotate(axis_angle_matrix(self.up, dyaw), p)
        dp = self._clamped_pitch(dpitch)
        if dp:
            self._rotate(axis_angle_matrix(self.right, dp), p)

    def look(self, dyaw: float, dpitch: float) -> None:
        """Fly-mode mouse look: rotate about the eye (the eye stays put)."""
        e = self.state.eye.copy()
        self._rotate(axis_angle_matrix(self.up, dyaw), e)
        dp = self._clamped_pitch(dpitch)
        if dp:
            self._rotate(axis_angle_matrix(self.right, dp), e)

    def pan(self, dx_px: float, dy_px: float, height: int) -> None:
        """Drag the scene by (dx, dy) pixels: a point at pivot depth follows the mouse exactly."""
        s = self.state
        world_per_px = s.distance * 2.0 * math.tan(0.5 * s.fov_y) / height
        s.eye = s.eye - (dx_px * self.right + dy_px * self.down) * world_per_px

    def zoom(self, steps: float, factor: float = 0.85) -> None:
        """Dolly toward the pivot: the distance is multiplied by factor**steps."""
        s = self.state
        p = self.pivot
        s.distance = max(MIN_DISTANCE, s.distance * factor**steps)
        s.eye = p - s.distance * s.R[2]

    def fly(self, forward: float, right: float, up: float) -> None:
        """Move eye and pivot together by world distances along view forward, view right and world up."""
        self.state.eye = self.state.eye + forward * self.forward + right * self.right + up * self.up

    def set_fov(self, fov_y_deg: float) -> None:
        self.state.fov_y = math.radians(float(np.clip(fov_y_deg, 5.0, 150.0)))

    def snap(self, cam: Camera, pivot: np.ndarray | None = None) -> None:
        """Jump to a training camera (pose and vertical field of view)."""
        self.state = _state_of(cam, pivot, self.state.distance)

    def reset(self) -> None:
        assert self.home is not None
        self.state = self.home.copy()


def _state_of(cam: Camera, pivot: np.ndarray | None, default_distance: float = 1.0) -> ViewState:
    R = _orthonormalize(cam.R.copy())
    eye = cam.center.copy()
    d = default_distance
    if pivot is not None:
        d = float((np.asarray(pivot, dtype=np.float64) - eye) @ R[2])
        if d <= MIN_DISTANCE:
            d = max(float(np.linalg.norm(np.asarray(pivot) - eye)), default_distance)
    return ViewState(eye=eye, R=R, distance=d, fov_y=cam.fov_y())


def _orthonormalize(R: np.ndarray) -> np.ndarray:
    """Nearest rotation (keeps accumulated float error from shearing the camera)."""
    u, _, vt = np.linalg.svd(R)
    Q = u @ vt
    if np.linalg.det(Q) < 0:
        u[:, -1] *= -1
        Q = u @ vt
    return Q
