"""Rotations of cameras and scene objects, in numpy float64: 3x3 matrices, rotation vectors
(axis * angle in radians) and unit quaternions (w, x, y, z) with the Hamilton product.

Right-handed throughout: a positive angle turns counter-clockwise about its axis seen from the
axis's tip. ``quat_exp``/``quat_log`` map rotation vectors to unit quaternions and back, so
``q * exp(omega * s)`` turns a frame at constant body angular velocity ``omega``; ``log`` and
the slerps take the short way round (angle <= pi): ``q`` and ``-q`` are the same rotation.
(The rasterizer's batched, differentiable quaternion -> matrix of Gaussians is torch code of its
own: :func:`atgs.render.projection.quat_to_rotmat`.)
"""

from __future__ import annotations

import math

import numpy as np


# --- matrices and rotation vectors ------------------------------------------------------------

def _rodrigues(k: np.ndarray, angle: float) -> np.ndarray:
    """Rotation by ``angle`` about the unit axis ``k``."""
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * (K @ K)


def axis_angle_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation by ``angle`` radians about ``axis`` (any non-zero length)."""
    a = np.asarray(axis, dtype=np.float64)
    return _rodrigues(a / np.linalg.norm(a), angle)


def rotvec_to_matrix(r: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle) -> rotation matrix."""
    r = np.asarray(r, np.float64).reshape(3)
    angle = float(np.linalg.norm(r))
    if angle < 1e-12:
        return np.eye(3)
    return _rodrigues(r / angle, angle)


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle, angle in [0, pi]) of a rotation matrix, stable near 0 and pi."""
    R = np.asarray(R, np.float64)
    cos = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    angle = float(np.arccos(cos))
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if angle < 1e-8:
        return 0.5 * w
    if np.pi - angle < 1e-4:  # near pi the skew part vanishes: take the axis from R + I
        B = 0.25 * (R + R.T) + 0.5 * np.eye(3)  # symmetric part: (1+cos)/2 I + (1-cos)/2 k k^T
        axis = np.sqrt(np.clip(np.diag(B), 0.0, None))
        k = int(np.argmax(axis))
        axis = B[k] / axis[k]
        axis /= np.linalg.norm(axis)
        if w @ axis < 0:
            axis = -axis
        return axis * angle
    return w * (angle / (2.0 * np.sin(angle)))


def matrix_slerp(R0: np.ndarray, R1: np.ndarray, s: float) -> np.ndarray:
    """Constant-speed rotation from R0 (s = 0) to R1 (s = 1) along the shortest arc; both turn
    vectors into the same frame (R @ v), e.g. camera-to-world rotations."""
    return R0 @ rotvec_to_matrix(s * matrix_to_rotvec(R0.T @ R1))


# --- unit quaternions ---------------------------------------------------------------------------

def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product: the rotation b, then a."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ])  # fmt: skip


def quat_conj(q: np.ndarray) -> np.ndarray:
    """The inverse of a unit quaternion."""
    return np.array([q[0], -q[1], -q[2], -q[3]])


def quat_exp(v: np.ndarray) -> np.ndarray:
    """Rotation vector -> unit quaternion (rotation by |v| about v / |v|)."""
    v = np.asarray(v, dtype=np.float64)
    angle = float(np.linalg.norm(v))
    # sin(angle / 2) / angle, smooth through 0 (np.sinc(x) = sin(pi x) / (pi x))
    k = 0.5 * float(np.sinc(angle / (2.0 * math.pi)))
    return np.array([math.cos(0.5 * angle), k * v[0], k * v[1], k * v[2]])


def quat_log(q: np.ndarray) -> np.ndarray:
    """Unit quaternion -> rotation vector of the short way round (angle in [0, pi])."""
    q = np.asarray(q, dtype=np.float64)
    if q[0] < 0.0:
        q = -q
    n = float(np.linalg.norm(q[1:]))
    if n == 0.0:
        return np.zeros(3)
    return (2.0 * math.atan2(n, q[0]) / n) * q[1:]


def quat_slerp(a: np.ndarray, b: np.ndarray, s: float) -> np.ndarray:
    """Constant-speed rotation from a (s = 0) to b (s = 1), the short way round."""
    return quat_mul(a, quat_exp(s * quat_log(quat_mul(quat_conj(a), b))))


def quat_normalized(q: np.ndarray) -> np.ndarray:
    return np.asarray(q, dtype=np.float64) / float(np.linalg.norm(q))


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a quaternion of any non-zero norm."""
    w, x, y, z = quat_normalized(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])  # fmt: skip


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit quaternion with w >= 0 (Shepperd: divide by the largest term)."""
    R = np.asarray(R, dtype=np.float64)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    diag = (tr, R[0, 0], R[1, 1], R[2, 2])
    i = int(np.argmax(diag))
    if i == 0:
        s = 2.0 * math.sqrt(max(1.0 + tr, 1e-300))
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif i == 1:
        s = 2.0 * math.sqrt(max(1.0 + R[0, 0] - R[1, 1] - R[2, 2], 1e-300))
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif i == 2:
        s = 2.0 * math.sqrt(max(1.0 + R[1, 1] - R[0, 0] - R[2, 2], 1e-300))
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(max(1.0 + R[2, 2] - R[0, 0] - R[1, 1], 1e-300))
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = quat_normalized(np.array(q))
    return -q if q[0] < 0 else q
