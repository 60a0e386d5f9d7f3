"""Camera control math against hand-computed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from atgs.cameras import Camera, look_at
from atgs.viewer.camera_control import CameraControl, intrinsics


def _control(eye=(4.0, 0.0, 0.0), target=(0.0, 0.0, 0.0)) -> CameraControl:
    K = intrinsics(200, 100, math.radians(60))
    cam = Camera("c", 200, 100, K, look_at(np.array(eye), np.array(target), np.array([0, 0, 1.0])))
    return CameraControl.from_camera(cam, pivot=np.array(target), up=np.array([0, 0, 1.0]))


def test_from_camera_round_trips_the_pose_and_fov() -> None:
    c = _control()
    cam = c.camera(200, 100)
    np.testing.assert_allclose(cam.center, [4, 0, 0], atol=1e-12)
    np.testing.assert_allclose(cam.forward, [-1, 0, 0], atol=1e-12)
    assert cam.fov_y() == pytest.approx(math.radians(60))
    assert c.state.distance == pytest.approx(4.0)
    np.testing.assert_allclose(c.pivot, [0, 0, 0], atol=1e-12)
    # image up is world +z: a point above the pivot projects above the image center
    uv, _ = cam.project(np.array([[0, 0, 1.0]]))
    assert uv[0, 1] < 50 and uv[0, 0] == pytest.approx(100)


def test_orbit_yaw_quarter_turn_by_hand() -> None:
    c = _control()
    c.orbit(math.pi / 2, 0.0)  # right-handed about +z: (4,0,0) -> (0,4,0)
    np.testing.assert_allclose(c.state.eye, [0, 4, 0], atol=1e-12)
    np.testing.assert_allclose(c.forward, [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(c.pivot, [0, 0, 0], atol=1e-12)
    c.orbit(3 * math.pi / 2, 0.0)
    np.testing.assert_allclose(c.state.eye, [4, 0, 0], atol=1e-12)


def test_orbit_pitch_keeps_pivot_and_distance_and_stops_at_pole() -> None:
    c = _control()
    c.orbit(0.0, -math.radians(30))  # view direction lowered by 30 deg: camera rises
    np.testing.assert_allclose(c.state.eye, [4 * math.cos(math.radians(30)), 0, 4 * math.sin(math.radians(30))], atol=1e-12)
    np.testing.assert_allclose(c.pivot, [0, 0, 0], atol=1e-12)
    c.orbit(0.0, -math.radians(200))  # would pass over the pole: clamped 2 deg short of it
    polar = math.degrees(math.acos(c.forward @ np.array([0, 0, 1.0])))
    assert polar == pytest.approx(178.0, abs=1e-6)
    assert np.linalg.norm(c.state.eye - c.pivot) == pytest.approx(4.0)


def test_pan_moves_the_pivot_by_exactly_the_mouse_delta() -> None:
    c = _control()
    before = c.camera(200, 100)
    pivot = c.pivot.copy()
    c.pan(12.0, -7.0, height=100)
    uv, z = c.camera(200, 100).project(pivot[None])
    uv0, _ = before.project(pivot[None])
    np.testing.assert_allclose(uv[0] - uv0[0], [12.0, -7.0], atol=1e-9)
    assert z[0] == pytest.approx(4.0)


def test_zoom_dollies_toward_the_pivot() -> None:
    c = _control()
    c.zoom(2.0, factor=0.5)
    np.testing.assert_allclose(c.state.eye, [1, 0, 0], atol=1e-12)
    assert c.state.distance == pytest.approx(1.0)
    c.zoom(-1.0, factor=0.5)
    np.testing.assert_allclose(c.state.eye, [2, 0, 0], atol=1e-12)


def test_fly_and_look() -> None:
    c = _control()
    c.fly(forward=1.0, right=0.5, up=0.25)  # forward -x, right = +y when looking down -x with z up
    np.testing.assert_allclose(c.state.eye, [3, 0.5, 0.25], atol=1e-12)
    eye = c.state.eye.copy()
    c.look(math.pi / 2, 0.0)
    np.testing.assert_allclose(c.state.eye, eye, atol=1e-12)
    np.testing.assert_allclose(c.forward, [0, -1, 0], atol=1e-12)
    c.look(0.0, math.radians(45))  # view raised by 45 degrees
    np.testing.assert_allclose(c.forward, [0, -math.sqrt(0.5), math.sqrt(0.5)], atol=1e-12)


def test_fov_snap_and_reset() -> None:
    c = _control()
    c.set_fov(90.0)
    assert c.camera(200, 100).K[1, 1] == pytest.approx(50.0)  # f = (H/2) / tan(45 deg)
    other = Camera("o", 640, 480, np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]),
                   look_at(np.array([0, 3.0, 1.0]), np.zeros(3), np.array([0, 0, 1.0])))
    c.snap(other, pivot=np.zeros(3))
    snapped = c.camera(640, 480)
    np.testing.assert_allclose(snapped.w2c, other.w2c, atol=1e-12)
    np.testing.assert_allclose(snapped.K, other.K, atol=1e-9)
    c.reset()
    np.testing.assert_allclose(c.camera(200, 100).center, [4, 0, 0], atol=1e-12)
    assert c.camera(200, 100).fov_y() == pytest.approx(math.radians(60))
