"""Camera format round trips: a known 3D point lands on the same pixel through every format.

The COLMAP check projects with pycolmap's own camera model (an independent implementation)."""

from __future__ import annotations

import numpy as np
import pytest

from atgs.cameras import Camera, look_at
from atgs.data import camera_formats as cf
from atgs.data.errors import DataError


def _cams(dist: bool = False) -> list[Camera]:
    rng = np.random.default_rng(3)
    out = []
    for i in range(4):
        eye = np.array([4 * np.cos(i), 4 * np.sin(i), 1.0 + 0.3 * i])
        K = np.array([[300.0 + 10 * i, 0, 160 + 3.3 * i], [0, 305.0 + 10 * i, 120 - 2.1 * i], [0, 0, 1]])
        d = np.array([0.05, -0.02, 0.001, -0.0005, 0.0]) * (i + 1) if dist else None
        out.append(Camera(f"cam{i:02d}", 320, 240, K, look_at(eye, rng.normal(size=3) * 0.2), d))
    return out


POINTS = np.array([[0.1, -0.2, 0.3], [0.5, 0.4, -0.1], [-0.3, 0.2, 0.8]])


def _gl_pixel(cam: Camera, X: np.ndarray) -> np.ndarray:
    clip = cam.gl_projection(0.1, 100.0) @ cam.gl_view() @ np.append(X, 1.0)
    ndc = clip[:3] / clip[3]
    return np.array([(ndc[0] + 1) * cam.width / 2, (1 - ndc[1]) * cam.height / 2])


def test_look_at_keeps_up_up() -> None:
    cam = Camera("c", 200, 100, np.array([[100, 0, 100], [0, 100, 50], [0, 0, 1.0]]),
                 look_at(np.array([5.0, 0, 1]), np.zeros(3)))
    uv, z = cam.project(np.array([[0, 0, 0.0], [0, 0, 1.0], [0, 1.0, 0]]))
    assert z.min() > 0
    assert uv[1, 1] < uv[0, 1]  # higher in the world = higher in the image (smaller v)
    assert uv[2, 0] > uv[0, 0]  # camera on +x looking at -x: world +y is to the right
    assert np.isclose(np.linalg.det(cam.R), 1.0)


@pytest.mark.parametrize("dist", [False, True])
def test_colmap_round_trip_and_projection(dist: bool) -> None:
    cams = _cams(dist)
    rec = cf.cameras_to_reconstruction(cams, [f"{c.name}.png" for c in cams])
    back = cf.cameras_from_reconstruction(rec)
    for c, b in zip(cams, back):
        assert b.name == c.name
        np.testing.assert_allclose(b.w2c, c.w2c, atol=1e-12)
        np.testing.assert_allclose(b.K, c.K, atol=1e-12)
        img = rec.images[cams.index(c) + 1]
        col = rec.cameras[img.camera_id]
        for X in POINTS:
            ours, _ = c.project(X[None])
            theirs = col.img_from_cam(img.cam_from_world() * X)
            np.testing.assert_allclose(ours[0], np.asarray(theirs).ravel(), atol=1e-9)


def test_poses_bounds_round_trip_and_axes() -> None:
    K = np.array([[280.0, 0, 160], [0, 280.0, 120], [0, 0, 1]])
    cams = [Camera(f"cam{i:02d}", 320, 240, K, look_at(np.array([3.0, i - 1.0, 1.0]), np.zeros(3))) for i in range(3)]
    arr = cf.cameras_to_poses_bounds(cams, np.array([0.5, 20.0]))
    assert arr.shape == (3, 17)
    # LLFF convention, checked by hand: column 0 of the 3x5 block is the camera's "down" axis
    # in world coordinates = OpenCV +y; column 2 ("back") = -forward
    m = arr[0, :15].reshape(3, 5)
    np.testing.assert_allclose(m[:, 0], cams[0].c2w[:3, 1], atol=1e-12)
    np.testing.assert_allclose(m[:, 2], -cams[0].forward, atol=1e-12)
    np.testing.assert_allclose(m[:, 4], [240, 320, 280])
    back, nf = cf.cameras_from_poses_bounds(arr, [c.name for c in cams])
    np.testing.assert_allclose(nf, [[0.5, 20.0]] * 3)
    for c, b in zip(cams, back):
        np.testing.assert_allclose(b.w2c, c.w2c, atol=1e-12)
        np.testing.assert_allclose(b.project(POINTS)[0], c.project(POINTS)[0], atol=1e-9)
    # frames stored at half resolution: intrinsics follow
    half, _ = cf.cameras_from_poses_bounds(arr, [c.name for c in cams], [(160, 120)] * 3)
    np.testing.assert_allclose(half[0].project(POINTS)[0], cams[0].project(POINTS)[0] / 2, atol=1e-9)


def test_poses_bounds_count_mismatch_names_file() -> None:
    K = np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]])
    arr = cf.cameras_to_poses_bounds([Camera("a", 320, 240, K, np.eye(4))], [1, 2])
    with pytest.raises(DataError, match=r"poses_bounds.npy: 1 poses for 2 videos"):
        cf.cameras_from_poses_bounds(arr, ["cam00", "cam01"])


def test_easyvolcap_round_trip(tmp_path) -> None:
    cams = _cams(dist=True)
    cf.write_easyvolcap(tmp_path, cams)
    back = cf.read_easyvolcap(tmp_path)
    for c, b in zip(cams, back):
        assert b.name == c.name and (b.width, b.height) == (c.width, c.height)
        np.testing.assert_allclose(b.w2c, c.w2c, atol=1e-12)
        np.testing.assert_allclose(b.dist, c.dist, atol=1e-15)
        np.testing.assert_allclose(b.project(POINTS)[0], c.project(POINTS)[0], atol=1e-9)


def test_easyvolcap_reads_rodrigues_only_and_crlf(tmp_path) -> None:
    """Files written by OpenCV use CRLF and may only carry the Rodrigues vector R_<cam>."""
    cam = _cams()[1]
    cf.write_easyvolcap(tmp_path, [cam])
    extri = (tmp_path / "extri.yml").read_text()
    start = extri.index("Rot_")
    end = extri.index("T_", start)
    (tmp_path / "extri.yml").write_text((extri[:start] + extri[end:]).replace("\n", "\r\n"))
    back = cf.read_easyvolcap(tmp_path)[0]
    np.testing.assert_allclose(back.w2c, cam.w2c, atol=1e-12)


def test_gl_matrices_project_to_same_pixel_and_invert() -> None:
    for cam in _cams():
        for X in POINTS:
            np.testing.assert_allclose(_gl_pixel(cam, X), cam.project(X[None])[0][0], atol=1e-9)
        back = cf.camera_from_gl(cam.name, cam.width, cam.height, cam.gl_view(), cam.gl_projection(0.1, 100.0))
        np.testing.assert_allclose(back.K, cam.K, atol=1e-9)
        np.testing.assert_allclose(back.w2c, cam.w2c, atol=1e-12)


def test_unsupported_colmap_model_is_a_data_error() -> None:
    import pycolmap

    c = pycolmap.Camera(model="FULL_OPENCV", width=10, height=10, params=[5, 5, 5, 5] + [0.0] * 8, camera_id=1)
    with pytest.raises(DataError, match="FULL_OPENCV"):
        cf.camera_from_colmap(c, pycolmap.Rigid3d(), "x")
