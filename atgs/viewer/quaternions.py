"""Unit quaternions for camera rotations: (w, x, y, z), Hamilton product, numpy only.

``exp``/``log`` map between unit quaternions and rotation vectors (axis * angle in radians), so
``q * exp(omega * s)`` turns a frame at constant body angular velocity ``omega``. ``log`` always
takes the short way round (angle <= pi): ``q`` and ``-q`` are the same rotation.
"""

from __future__ import annotations

import math

import numpy as np


def mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ])  # fmt: skip


def conj(q: np.ndarray) -> np.ndarray:
    """The inverse of a unit quaternion."""
    return np.array([q[0], -q[1], -q[2], -q[3]])


def exp(v: np.ndarray) -> np.ndarray:
    """Rotation vector -> unit quaternion (rotation by |v| about v / |v|)."""
    v = np.asarray(v, dtype=np.float64)
    angle = float(np.linalg.norm(v))
    # sin(angle / 2) / angle, smooth through 0 (np.sinc(x) = sin(pi x) / (pi x))
    k = 0.5 * float(np.sinc(angle / (2.0 * math.pi)))
    return np.array([math.cos(0.5 * angle), k * v[0], k * v[1], k * v[2]])


def log(q: np.ndarray) -> np.ndarray:
    """Unit quaternion -> rotation vector of the short way round (angle in [0, pi])."""
    q = np.asarray(q, dtype=np.float64)
    if q[0] < 0.0:
        q = -q
    n = float(np.linalg.norm(q[1:]))
    if n == 0.0:
        return np.zeros(3)
    return (2.0 * math.atan2(n, q[0]) / n) * q[1:]


def slerp(a: np.ndarray, b: np.ndarray, s: float) -> np.ndarray:
    """Constant-speed rotation from a (s = 0) to b (s = 1), the short way round."""
    return mul(a, exp(s * log(mul(conj(a), b))))


def normalized(q: np.ndarray) -> np.ndarray:
    return np.asarray(q, dtype=np.float64) / float(np.linalg.norm(q))


def to_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = normalized(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])  # fmt: skip


def from_matrix(R: np.ndarray) -> np.ndarray:
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
    q = normalized(np.array(q))
    return -q if q[0] < 0 else q
