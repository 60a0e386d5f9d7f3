"""atgs.rotations against scipy.spatial.transform (an independent implementation), plus the
cases that need care: angles near 0 and pi, the short way round, quaternion signs."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from atgs.rotations import (axis_angle_matrix, matrix_slerp, matrix_to_rotvec, quat_conj, quat_exp, quat_from_matrix,
                            quat_log, quat_mul, quat_slerp, quat_to_matrix, rotvec_to_matrix)

RANDOM = [Rotation.random(random_state=i) for i in range(20)]


def _scalar_first(r: Rotation) -> np.ndarray:
    x, y, z, w = r.as_quat()  # scipy is scalar-last
    return np.array([w, x, y, z])


def test_matrices_from_axes_and_rotation_vectors_match_scipy() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        axis, angle = rng.normal(size=3) * 3, rng.uniform(-2 * math.pi, 2 * math.pi)
        ref = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()
        np.testing.assert_allclose(axis_angle_matrix(axis, angle), ref, atol=1e-12)
    for r in RANDOM:
        np.testing.assert_allclose(rotvec_to_matrix(r.as_rotvec()), r.as_matrix(), atol=1e-12)
        np.testing.assert_allclose(matrix_to_rotvec(r.as_matrix()), r.as_rotvec(), atol=1e-9)
    R = axis_angle_matrix(np.array([0, 0, 2.0]), math.pi / 2)  # right-handed: x turns to y
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-12)


def test_rotation_vectors_round_trip_near_zero_and_pi() -> None:
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    for angle in (1e-9, 0.3, 2.0, np.pi - 1e-6, np.pi):
        R = rotvec_to_matrix(axis * angle)
        np.testing.assert_allclose(R, Rotation.from_rotvec(axis * angle).as_matrix(), atol=1e-12)
        r = matrix_to_rotvec(R)
        np.testing.assert_allclose(rotvec_to_matrix(r), R, atol=1e-7)
        assert np.linalg.norm(r) <= np.pi + 1e-12


def test_quaternions_match_scipy() -> None:
    for a, b in zip(RANDOM, RANDOM[1:]):
        q = quat_from_matrix(a.as_matrix())
        assert q[0] >= 0 and abs(abs(q @ _scalar_first(a)) - 1.0) < 1e-12
        np.testing.assert_allclose(quat_to_matrix(q), a.as_matrix(), atol=1e-12)
        np.testing.assert_allclose(quat_to_matrix(quat_exp(a.as_rotvec())), a.as_matrix(), atol=1e-12)
        np.testing.assert_allclose(quat_to_matrix(quat_mul(_scalar_first(a), _scalar_first(b))), (a * b).as_matrix(),
                                   atol=1e-12)  # the rotation b, then a
        np.testing.assert_allclose(quat_to_matrix(quat_conj(_scalar_first(a))), a.inv().as_matrix(), atol=1e-12)


def test_quaternion_round_trips_and_short_way() -> None:
    for i in range(20):
        R = Rotation.random(random_state=i).as_matrix()
        q = quat_from_matrix(R)
        np.testing.assert_allclose(quat_to_matrix(q), R, atol=1e-12)
        np.testing.assert_allclose(abs(q @ Rotation.from_matrix(R).as_quat(scalar_first=True)), 1.0, atol=1e-12)
        v = Rotation.from_matrix(R).as_rotvec()
        np.testing.assert_allclose(quat_log(quat_exp(v)), v, atol=1e-12)
    # 350 degrees about z is 10 degrees the other way: log takes the short way
    q = quat_exp(np.array([0.0, 0.0, math.radians(350.0)]))
    np.testing.assert_allclose(quat_log(q), [0.0, 0.0, math.radians(-10.0)], atol=1e-12)


def test_slerps_match_scipy() -> None:
    for a, b in zip(RANDOM, RANDOM[1:]):
        ref = Slerp([0.0, 1.0], Rotation.concatenate([a, b]))
        for s in (0.0, 0.25, 0.5, 0.9, 1.0):
            want = ref([s]).as_matrix()[0]
            np.testing.assert_allclose(quat_to_matrix(quat_slerp(_scalar_first(a), _scalar_first(b), s)), want,
                                       atol=1e-12)
            np.testing.assert_allclose(matrix_slerp(a.as_matrix(), b.as_matrix(), s), want, atol=1e-9)
    # the short way: from the identity to 350 degrees about z passes through -5 degrees
    half = matrix_slerp(np.eye(3), axis_angle_matrix(np.array([0, 0, 1.0]), math.radians(350)), 0.5)
    np.testing.assert_allclose(half, Rotation.from_euler("z", -5, degrees=True).as_matrix(), atol=1e-12)
