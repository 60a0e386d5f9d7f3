"""Camera path interpolation (atgs/viewer/camera_path.py) against analytic motions, finite
differences and scipy; the keyframe editor of the player's path panel."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.interpolate import PchipInterpolator
from scipy.spatial.transform import Rotation

from atgs.viewer.camera_path import CameraPath, PathKey, PathSpline, frame_position
from atgs.viewer.path_editor import PathEditor

TIMES = np.array([0.0, 0.13, 0.4, 0.55, 1.0])  # uneven on purpose


def key(video_t: float, c2w: np.ndarray, eye: np.ndarray, fov: float = 50.0, scene_t: float = 0.0) -> PathKey:
    w2c = np.eye(4)
    w2c[:3, :3] = c2w.T
    w2c[:3, 3] = -c2w.T @ eye
    return PathKey(video_t, w2c, fov, scene_t)


def random_keys(seed: int = 0, times: np.ndarray = TIMES) -> list[PathKey]:
    rng = np.random.default_rng(seed)
    return [key(u, Rotation.random(random_state=seed * 100 + i).as_matrix(), rng.normal(size=3) * 3,
                30 + 40 * rng.random(), rng.random()) for i, u in enumerate(times)]


def angular_velocity(sp: PathSpline, u0: float, u1: float) -> np.ndarray:
    """Body-frame rotation from the pose at u0 to the pose at u1, per unit time."""
    R0, R1 = sp.pose_at(u0).R.T, sp.pose_at(u1).R.T  # camera-to-world
    return Rotation.from_matrix(R0.T @ R1).as_rotvec() / (u1 - u0)


def test_passes_through_every_keyframe_exactly() -> None:
    keys = random_keys(1)
    sp = PathSpline(keys)
    for k in keys:
        p = sp.pose_at(k.video_t)
        np.testing.assert_array_equal(p.R, k.R)
        np.testing.assert_array_equal(p.eye, k.eye)
        assert p.fov_y_deg == k.fov_y_deg and p.scene_t == k.scene_t
    # and just next to each keyframe it is continuous (no jump to another branch)
    for k in keys[1:-1]:
        for u in (k.video_t - 1e-9, k.video_t + 1e-9):
            p = sp.pose_at(u)
            assert np.abs(p.eye - k.eye).max() < 1e-6 and np.abs(p.R - k.R).max() < 1e-6


def test_position_and_rotation_are_c1_at_the_keyframes() -> None:
    """One-sided finite-difference derivatives agree at every inner keyframe (to O(h)), while
    the same test on piecewise-linear interpolation of the same keyframes sees the jump."""
    keys = random_keys(2)
    sp = PathSpline(keys)
    h = 1e-6
    for k in keys[1:-1]:
        u = k.video_t
        left = (sp.pose_at(u).eye - sp.pose_at(u - h).eye) / h
        right = (sp.pose_at(u + h).eye - sp.pose_at(u).eye) / h
        assert np.abs(left - right).max() < 1e-3 * np.abs(left).max(), (left, right)
        w_left, w_right = angular_velocity(sp, u - h, u), angular_velocity(sp, u, u + h)
        assert np.abs(w_left - w_right).max() < 1e-3 * np.abs(w_left).max(), (w_left, w_right)
    # the reference check: a piecewise-linear path through the same keyframes has kinks it would catch
    eyes = np.stack([k.eye for k in keys])
    i = 2
    lin_left = (eyes[i] - eyes[i - 1]) / (TIMES[i] - TIMES[i - 1])
    lin_right = (eyes[i + 1] - eyes[i]) / (TIMES[i + 1] - TIMES[i])
    assert np.abs(lin_left - lin_right).max() > 1e-3 * np.abs(lin_left).max()


def test_reproduces_constant_acceleration_and_constant_angular_velocity() -> None:
    """Keyframes sampled (unevenly) from p(t) = a + b t + c t^2 and R(t) = exp(w t): the path is
    that motion everywhere, not only at the keyframes (Catmull-Rom with time knots is exact for
    quadratics; the rotation spline for one-parameter rotations)."""
    rng = np.random.default_rng(3)
    a, b, c = rng.normal(size=(3, 3))
    w = np.array([0.3, -1.2, 2.0])
    keys = [key(u, Rotation.from_rotvec(w * u).as_matrix(), a + b * u + c * u * u) for u in TIMES]
    sp = PathSpline(keys)
    for u in np.linspace(0, 1, 37):
        p = sp.pose_at(u)
        np.testing.assert_allclose(p.eye, a + b * u + c * u * u, atol=1e-12)
        np.testing.assert_array_equal(sp.eye_at(u), p.eye)
        np.testing.assert_allclose(p.R.T, Rotation.from_rotvec(w * u).as_matrix(), atol=1e-12)


def test_two_keyframes_are_lerp_and_constant_speed_slerp() -> None:
    R0, R1 = Rotation.random(random_state=5), Rotation.random(random_state=6)
    e0, e1 = np.array([1.0, 2.0, 3.0]), np.array([-2.0, 0.5, 1.0])
    keys = [key(0.2, R0.as_matrix(), e0), key(0.9, R1.as_matrix(), e1)]
    sp = PathSpline(keys)
    from scipy.spatial.transform import Slerp

    ref = Slerp([0.2, 0.9], Rotation.concatenate([R0, R1]))
    for u in np.linspace(0.2, 0.9, 11):
        s = (u - 0.2) / 0.7
        p = sp.pose_at(u)
        np.testing.assert_allclose(p.eye, (1 - s) * e0 + s * e1, atol=1e-12)
        np.testing.assert_allclose(p.R.T, ref([u]).as_matrix()[0], atol=1e-12)
    # before the first and after the last keyframe the path holds
    np.testing.assert_array_equal(sp.pose_at(0.0).eye, keys[0].eye)
    np.testing.assert_array_equal(sp.pose_at(1.0).R, keys[1].R)


def test_rotations_stay_normalized_and_take_the_short_way_round() -> None:
    yaw = lambda deg: Rotation.from_euler("z", deg, degrees=True).as_matrix()  # noqa: E731
    sp = PathSpline([key(0.0, yaw(0.0), np.zeros(3)), key(1.0, yaw(350.0), np.zeros(3))])
    angles = []
    for u in np.linspace(0, 1, 21):
        R = sp.pose_at(u).R.T
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
        angles.append(Rotation.from_matrix(R).as_euler("zyx", degrees=True)[0])
    np.testing.assert_allclose(angles, -10.0 * np.linspace(0, 1, 21), atol=1e-9)  # 10 degrees, not 350
    # random keyframes: every interpolated quaternion is unit length
    sp = PathSpline(random_keys(4))
    for u in np.linspace(0, 1, 50):
        R = sp.pose_at(u).R
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)


def test_fov_and_scene_time_are_monotone_pchip() -> None:
    keys = random_keys(7)
    for k, s in zip(keys, (0.0, 0.3, 0.3, 0.8, 0.6)):  # a hold (0.3, 0.3) and a turn back
        k.scene_t = s
    sp = PathSpline(keys)
    ref_fov = PchipInterpolator(TIMES, [k.fov_y_deg for k in keys])
    ref_t = PchipInterpolator(TIMES, [k.scene_t for k in keys])
    for u in np.linspace(0, 1, 41):
        p = sp.pose_at(u)
        assert p.fov_y_deg == pytest.approx(float(ref_fov(u)), abs=1e-12)
        assert p.scene_t == pytest.approx(float(ref_t(u)), abs=1e-12)
    for u in np.linspace(0.13, 0.4, 9):  # time holds still between equal keyframes
        assert sp.pose_at(u).scene_t == pytest.approx(0.3, abs=1e-15)


def test_render_plan_frames_and_cameras() -> None:
    path = CameraPath(random_keys(8), duration_s=1.5, fps=10.0)
    assert path.frame_count() == 15 and path.frame_count(fps=4.0) == 6
    assert [frame_position(i, 5) for i in range(5)] == [0.0, 0.25, 0.5, 0.75, 1.0]
    cams, times = path.render_plan(64, 48)
    assert len(cams) == len(times) == 15
    for i, (cam, t) in enumerate(zip(cams, times)):
        p = path.pose_at(i / 14)
        assert t == p.scene_t and (cam.width, cam.height) == (64, 48)
        np.testing.assert_allclose(cam.center, p.eye, atol=1e-12)
        assert math.degrees(cam.fov_y()) == pytest.approx(p.fov_y_deg, abs=1e-9)
        assert (cam.cx, cam.cy) == (32.0, 24.0) and cam.fx == cam.fy
    with pytest.raises(ValueError):
        PathSpline([])
    with pytest.raises(ValueError):
        PathSpline(random_keys(9, np.array([0.0, 0.5, 0.5])))


def test_editor_add_reorder_update_delete_keep_video_order() -> None:
    ks = random_keys(10)
    ed = PathEditor()
    for k in ks[:3]:
        ed.add(k)
    assert [k.video_t for k in ed.keys] == [0.0, 0.5, 1.0] and ed.selected == 2
    ed.selected = 0
    ed.add(ks[3])  # after the selected one; even timing respaces
    assert ed.selected == 1 and [k.video_t for k in ed.keys] == [0.0, 1 / 3, 2 / 3, 1.0]
    np.testing.assert_array_equal(ed.keys[1].w2c, ks[3].w2c)
    ed.move(1, +1)  # reorder: contents swap, time slots stay
    np.testing.assert_array_equal(ed.keys[2].w2c, ks[3].w2c)
    assert ed.selected == 2 and [k.video_t for k in ed.keys] == [0.0, 1 / 3, 2 / 3, 1.0]
    ed.update(0, ks[4])
    np.testing.assert_array_equal(ed.keys[0].w2c, ks[4].w2c)
    assert ed.keys[0].video_t == 0.0
    ed.delete(2)
    assert len(ed.keys) == 3 and [k.video_t for k in ed.keys] == [0.0, 0.5, 1.0]
    # manual timing: edits keep the other keyframes' times
    ed.set_even_timing(False)
    ed.set_video_t(1, 0.8)
    ed.set_video_t(1, 2.0)  # clamped before the next keyframe
    assert 0.8 < ed.keys[1].video_t < 1.0
    ed.selected = 0
    ed.add(ks[0])  # between 0 and the next: halfway
    assert ed.keys[1].video_t == pytest.approx(0.5 * ed.keys[2].video_t)
    ed.selected = len(ed.keys) - 1
    before = [k.video_t for k in ed.keys]
    ed.add(ks[1])  # after the last (at 1.0): the path is squeezed, the new segment gets an average share
    times = [k.video_t for k in ed.keys]
    assert times[-1] == 1.0 and np.all(np.diff(times) > 0)
    np.testing.assert_allclose(times[:-1], np.array(before) * 3 / 4)
    PathSpline(ed.keys)  # still a valid path


def test_editor_preview_clock_shows_every_frame_once() -> None:
    ed = PathEditor()
    for k in random_keys(11)[:3]:
        ed.add(k)
    ed.set_timing(duration_s=1.0, fps=8.0)
    ed.start_preview()
    shown = []
    while ed.previewing:
        ed.advance(1 / 8)  # the first call keeps frame 0 on screen for its UI frame
        shown.append(ed.frame)
    assert shown == [0, 1, 2, 3, 4, 5, 6, 7, 7]
    ed.seek(99)
    assert ed.frame == 7 and not ed.previewing
