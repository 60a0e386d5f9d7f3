"""Camera paths: keyframes -> one camera and one scene time per video frame. Pure numpy (no GL, no UI).

A keyframe pins, at a position ``video_t`` in [0, 1] of the video, a camera pose (OpenCV
world-to-camera, the project's convention), a vertical field of view and the scene time
``scene_t`` (normalized sequence time, as everywhere in ATGS) shown at that moment. Between
keyframes, all of it is interpolated in ``video_t``:

- position: a cubic Hermite spline whose tangent at each keyframe is the derivative of the
  parabola through it and its two neighbours, i.e. Catmull-Rom with the keyframe times as knots
  ("non-uniform Catmull-Rom"; at the two ends: the parabola through the first / last three).
  Why this one: it passes through every keyframe, is C1 in time (one tangent per keyframe, shared
  by both segments), is local (moving a keyframe bends only the nearby segments; a natural
  cubic spline is global and rings on unevenly spaced keyframes), and it reproduces constant
  velocity and constant acceleration exactly. Knots are the keyframe *times*, not the
  centripetal (sqrt distance) knots, because the video must reach each keyframe at its time: a
  centripetal parametrization re-times the path, and the speed would jump at every keyframe.
- rotation: the same construction on unit quaternions. The tangent at a keyframe is a body-frame
  angular velocity (the time-weighted average of the two adjacent constant-speed rotations), and
  each segment is a cubic Bezier curve built from slerps (De Casteljau on the rotation group)
  whose inner control points are the keyframes turned by a third of that velocity times the
  segment: exactly C1 in angular velocity, through every keyframe, unit length throughout, and
  each leg takes the short way round (350 degrees of yaw between two keyframes turn 10 degrees).
  Two keyframes give the constant-speed slerp.
- field of view and scene time: monotone cubic (Fritsch-Carlson / PCHIP) interpolation: C1,
  never outside the range of the neighbouring keyframes, and exactly constant between two equal
  values, so a path can hold time still (bullet time) or ease into a pause without the time
  running backwards, which a Catmull-Rom spline would do.

Before the first and after the last keyframe everything holds. Frame i of n sits at
``video_t = i / (n - 1)``, ``n = round(duration_s * fps)``. The JSON file format is in
:mod:`viewer.camera_path_file`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from atgs.cameras import Camera
from atgs.rotations import (quat_conj, quat_exp, quat_from_matrix, quat_log, quat_mul, quat_normalized, quat_slerp,
                             quat_to_matrix)
from atgs.viewer.camera_control import intrinsics


@dataclass
class PathKey:
    """One keyframe: where in the video, the camera there (OpenCV w2c, vertical fov), the scene time."""

    video_t: float
    w2c: np.ndarray
    fov_y_deg: float
    scene_t: float

    def __post_init__(self) -> None:
        self.video_t, self.fov_y_deg, self.scene_t = float(self.video_t), float(self.fov_y_deg), float(self.scene_t)
        self.w2c = np.asarray(self.w2c, dtype=np.float64).reshape(4, 4)

    @property
    def R(self) -> np.ndarray:
        """World-to-camera rotation (rows: right, down, forward)."""
        return self.w2c[:3, :3]

    @property
    def eye(self) -> np.ndarray:
        """Camera center in world coordinates."""
        return -self.R.T @ self.w2c[:3, 3]

    def copy(self) -> "PathKey":
        return PathKey(self.video_t, self.w2c.copy(), self.fov_y_deg, self.scene_t)


@dataclass
class PathPose:
    """The interpolated camera and scene time at one moment of the video."""

    eye: np.ndarray
    R: np.ndarray  # world-to-camera rotation
    fov_y_deg: float
    scene_t: float

    def camera(self, width: int, height: int, name: str = "path") -> Camera:
        """Square pixels, principal point at the image center (as the player's view)."""
        w2c = np.eye(4)
        w2c[:3, :3] = self.R
        w2c[:3, 3] = -self.R @ self.eye
        return Camera(name, width, height, intrinsics(width, height, math.radians(self.fov_y_deg)), w2c)


@dataclass
class CameraPath:
    """Keyframes in video order plus the video's duration and frame rate."""

    keys: list[PathKey] = field(default_factory=list)
    duration_s: float = 5.0
    fps: float = 30.0
    size: tuple[int, int] | None = None  # default video size (the player saves its window size)

    def frame_count(self, fps: float | None = None) -> int:
        """Video frames: duration x frame rate, at least one."""
        return max(1, int(round(self.duration_s * (self.fps if fps is None else fps))))

    def spline(self) -> "PathSpline":
        return PathSpline(self.keys)

    def pose_at(self, video_t: float) -> PathPose:
        return self.spline().pose_at(video_t)

    def render_plan(self, width: int, height: int, num_frames: int | None = None) -> tuple[list[Camera], list[float]]:
        """The camera and the scene time of each video frame (what atgs-render and the preview show)."""
        n = self.frame_count() if num_frames is None else int(num_frames)
        sp = self.spline()
        poses = [sp.pose_at(frame_position(i, n)) for i in range(n)]
        return [p.camera(width, height, f"path{i:05d}") for i, p in enumerate(poses)], [p.scene_t for p in poses]


def frame_position(i: int, n: int) -> float:
    """video_t of frame i of n: the first frame shows the start, the last the end of the path."""
    return 0.0 if n <= 1 else min(max(i, 0), n - 1) / (n - 1)


class PathSpline:
    """The interpolation of a list of keyframes (tangents computed once)."""

    def __init__(self, keys: Sequence[PathKey]) -> None:
        if not keys:
            raise ValueError("a camera path needs at least one keyframe")
        self.t = np.array([k.video_t for k in keys], dtype=np.float64)
        if np.any(np.diff(self.t) <= 0):
            raise ValueError(f"keyframe times must increase strictly, got {self.t.tolist()}")
        self.eye = np.stack([k.eye for k in keys])
        self.R = np.stack([k.R for k in keys])
        self.q = np.stack([quat_from_matrix(R.T) for R in self.R])  # camera-to-world rotations
        self.fov = np.array([k.fov_y_deg for k in keys])
        self.scene = np.array([k.scene_t for k in keys])
        self.m_eye = catmull_rom_tangents(self.t, self.eye)
        self.m_q = rotation_tangents(self.t, self.q)
        self.m_fov = pchip_tangents(self.t, self.fov)
        self.m_scene = pchip_tangents(self.t, self.scene)

    def _locate(self, u: float) -> tuple[int, float]:
        """(segment i, parameter s in [0, 1)) of video time u; s == 0 on keyframe i and beyond the ends."""
        if math.isnan(u):
            raise ValueError("video_t is NaN")
        t = self.t
        if u <= t[0]:
            return 0, 0.0
        if u >= t[-1]:
            return len(t) - 1, 0.0
        i = int(np.searchsorted(t, u, side="right")) - 1
        return i, float((u - t[i]) / (t[i + 1] - t[i]))

    def eye_at(self, video_t: float) -> np.ndarray:
        """The camera center alone (cheaper than :meth:`pose_at`: for drawing the path)."""
        i, s = self._locate(float(video_t))
        if s == 0.0:
            return self.eye[i].copy()
        d = self.t[i + 1] - self.t[i]
        return hermite(self.eye[i], self.eye[i + 1], self.m_eye[i] * d, self.m_eye[i + 1] * d, s)

    def pose_at(self, video_t: float) -> PathPose:
        i, s = self._locate(float(video_t))
        if s == 0.0:  # on a keyframe (or holding before / after the path): its values exactly
            return PathPose(self.eye[i].copy(), self.R[i].copy(), float(self.fov[i]), float(self.scene[i]))
        d = self.t[i + 1] - self.t[i]
        eye = hermite(self.eye[i], self.eye[i + 1], self.m_eye[i] * d, self.m_eye[i + 1] * d, s)
        q = rotation_bezier(self.q[i], self.q[i + 1], self.m_q[i] * d, self.m_q[i + 1] * d, s)
        fov = hermite(self.fov[i], self.fov[i + 1], self.m_fov[i] * d, self.m_fov[i + 1] * d, s)
        scene = hermite(self.scene[i], self.scene[i + 1], self.m_scene[i] * d, self.m_scene[i + 1] * d, s)
        return PathPose(eye, quat_to_matrix(q).T, float(fov), float(min(1.0, max(0.0, scene))))


def hermite(p0, p1, m0, m1, s: float):
    """Cubic Hermite on [0, 1]: values p0, p1 and derivatives (per unit s) m0, m1 at the ends."""
    s2, s3 = s * s, s * s * s
    return (2 * s3 - 3 * s2 + 1) * p0 + (s3 - 2 * s2 + s) * m0 + (3 * s2 - 2 * s3) * p1 + (s3 - s2) * m1


def _bessel_end(s_near: np.ndarray, s_far: np.ndarray, d_near: float, d_far: float) -> np.ndarray:
    """Derivative at an end of the parabola through the last three points (slopes s, durations d)."""
    return ((2 * d_near + d_far) * s_near - d_near * s_far) / (d_near + d_far)


def _bessel_inner(s_before: np.ndarray, s_after: np.ndarray, d_before: np.ndarray, d_after: np.ndarray) -> np.ndarray:
    """Derivative at the middle point of the parabola through three points."""
    return (d_after * s_before + d_before * s_after) / (d_before + d_after)


def catmull_rom_tangents(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Tangents (d p / d t) of Catmull-Rom with knots t: (K,) times, (K, D) points -> (K, D)."""
    K = len(t)
    m = np.zeros_like(p, dtype=np.float64)
    if K < 2:
        return m
    d = np.diff(t)
    s = np.diff(p, axis=0) / d[:, None]
    if K == 2:
        m[:] = s[0]
        return m
    m[1:-1] = _bessel_inner(s[:-1], s[1:], d[:-1, None], d[1:, None])
    m[0] = _bessel_end(s[0], s[1], d[0], d[1])
    m[-1] = _bessel_end(s[-1], s[-2], d[-1], d[-2])
    return m


def rotation_tangents(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Body-frame angular velocities (rad per unit t) at the keyframes: the Catmull-Rom rule on
    the segments' constant-speed rotations. A segment's body-frame velocity is the same all along
    it, so it applies unchanged at both its keyframes; the end rule needs the second segment's
    velocity expressed in the end keyframe's frame."""
    K = len(t)
    m = np.zeros((K, 3))
    if K < 2:
        return m
    d = np.diff(t)
    w = np.stack([quat_log(quat_mul(quat_conj(q[j]), q[j + 1])) / d[j] for j in range(K - 1)])
    if K == 2:
        m[:] = w[0]
        return m
    m[1:-1] = _bessel_inner(w[:-1], w[1:], d[:-1, None], d[1:, None])
    w1_at_0 = quat_to_matrix(quat_mul(quat_conj(q[0]), q[1])) @ w[1]
    w2_at_end = quat_to_matrix(quat_mul(quat_conj(q[-1]), q[-2])) @ w[-2]
    m[0] = _bessel_end(w[0], w1_at_0, d[0], d[1])
    m[-1] = _bessel_end(w[-1], w2_at_end, d[-1], d[-2])
    return m


def rotation_bezier(q0: np.ndarray, q1: np.ndarray, w0: np.ndarray, w1: np.ndarray, s: float) -> np.ndarray:
    """Cubic Bezier on unit quaternions by De Casteljau with slerps, from q0 (s = 0) to q1 (s = 1)
    with body angular velocities w0, w1 (per unit s) at the ends: like the Euclidean Bezier, its
    end velocity is 3x the first leg, so the inner control points are q exp(+-w / 3)."""
    a = quat_mul(q0, quat_exp(w0 / 3.0))
    b = quat_mul(q1, quat_exp(-w1 / 3.0))
    r0, r1, r2 = quat_slerp(q0, a, s), quat_slerp(a, b, s), quat_slerp(b, q1, s)
    return quat_normalized(quat_slerp(quat_slerp(r0, r1, s), quat_slerp(r1, r2, s), s))


def pchip_tangents(t: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Fritsch-Carlson monotone tangents of scalar data (the rule of scipy's PchipInterpolator)."""
    K = len(t)
    m = np.zeros(K)
    if K < 2:
        return m
    h = np.diff(t)
    s = np.diff(y) / h
    if K == 2:
        m[:] = s[0]
        return m
    w1 = 2 * h[1:] + h[:-1]
    w2 = h[1:] + 2 * h[:-1]
    same_sign = s[:-1] * s[1:] > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        inner = (w1 + w2) / (w1 / s[:-1] + w2 / s[1:])
    m[1:-1] = np.where(same_sign, inner, 0.0)

    def end(s0: float, s1: float, h0: float, h1: float) -> float:
        d = ((2 * h0 + h1) * s0 - h0 * s1) / (h0 + h1)
        if np.sign(d) != np.sign(s0):
            return 0.0
        if np.sign(s0) != np.sign(s1) and abs(d) > 3 * abs(s0):
            return 3 * s0
        return d

    m[0] = end(s[0], s[1], h[0], h[1])
    m[-1] = end(s[-1], s[-2], h[-1], h[-2])
    return m
