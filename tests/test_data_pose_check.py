"""Poses checked against the images (atgs.data.pose_check): epipolar distances against an
independent point-to-line construction, mirrored worlds, camera-to-world matrices filed as
world-to-camera read back from rendered frames (many matches) and from where a wide rig looks
(too few), and a public Dynamic 3D Gaussians capture's shape end to end: three cameras numbered
from 1, no test_meta.json, no init_pt_cld.npz, five-digit frame names, masks for every camera,
more images than the metas list, and camera-to-world matrices of a mirrored world under ``w2c``."""

from __future__ import annotations

import contextlib
import io
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from atgs.cameras import Camera, look_at
from atgs.data.colmap_ops import ColmapOptions
from atgs.data.errors import DataError
from atgs.data.mvs import StereoConfig
from atgs.data.moving_points import MotionPointsConfig
from atgs.data.pose_check import (MIRROR_X, PoseCheckConfig, check_poses, epipolar_distances, inverted_reading,
                                  proper_world)
from atgs.data.prepare import PrepareConfig, prepare
from atgs.data.scene import PreparedScene
from atgs.data.sources import open_source
from atgs.data.synth.mesh_renderer import MeshRenderer
from atgs.data.synth.scene import SynthConfig, SynthScene
from builders import ring_cameras

FAST = dict(keyframes=1, progress=False, stereo=StereoConfig(enabled=False), motion=MotionPointsConfig(enabled=False))


def _project(cam: Camera, X: np.ndarray) -> np.ndarray:
    x = cam.R @ X + cam.t
    return (cam.K @ (x / x[2]))[:2]


def test_epipolar_distance_is_zero_on_the_line_and_bounded_by_the_point_to_line_distance() -> None:
    """The epipolar line of a's pixel in b is built independently: through b's projections of two
    points on a's ray. A true match lies on it; moved off it by d px, the Sampson distance (which
    shares the error between both images) lies between d/2 and d."""
    a, b = ring_cameras(2, size=(320, 240), radius=4.0)[0], ring_cameras(5, size=(320, 240), radius=4.0)[1]
    rng = np.random.default_rng(0)
    for _ in range(20):
        X = rng.normal(size=3) * 0.5
        xa, xb = _project(a, X), _project(b, X)
        assert epipolar_distances(a, b, xa[None], xb[None])[0] < 1e-6
        ray = np.linalg.inv(a.R) @ (np.linalg.inv(a.K) @ np.r_[xa, 1.0])
        p, q = (_project(b, a.center + s * ray) for s in (1.0, 6.0))
        normal = np.array([-(q - p)[1], (q - p)[0]]) / np.linalg.norm(q - p)
        d = rng.uniform(0.5, 6.0)
        s = epipolar_distances(a, b, xa[None], (xb + d * normal)[None])[0]
        assert d / 2 <= s <= d + 1e-6, (d, s)
    baseline_free = replace(b, w2c=a.w2c.copy())  # same centre: no epipolar geometry to agree with
    assert np.isinf(epipolar_distances(a, baseline_free, xa[None], xb[None])).all()


def test_a_mirrored_world_is_mirrored_back_and_projects_the_same() -> None:
    cams = ring_cameras(4, size=(64, 48))
    mirrored = [replace(c, w2c=c.w2c @ MIRROR_X) for c in cams]  # the same rig in a left-handed world
    assert all(np.linalg.det(c.R) < 0 for c in mirrored)
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        back, mirror = proper_world(mirrored, Path("meta.json"))
    assert mirror is not None and "mirrored" in err.getvalue()
    X = np.random.default_rng(1).normal(size=(10, 3))
    for m, c in zip(mirrored, back):
        assert np.linalg.det(c.R) > 0
        for x in X:  # a point of the file's world projects where its mirror image does in the scene's
            np.testing.assert_allclose(_project(m, x), _project(c, mirror[:3, :3] @ x), atol=1e-9)
    same, none = proper_world(cams, Path("meta.json"))
    assert none is None and same == cams
    with pytest.raises(DataError, match=r"meta.json: the rotations of camera\(s\) cam01 are mirror images") as e:
        proper_world([cams[0], mirrored[1], cams[2]], Path("meta.json"))
    assert "\n" not in str(e.value)


def test_the_inverted_reading_of_camera_to_world_matrices_in_a_mirrored_world_is_the_truth() -> None:
    truth = ring_cameras(3, size=(64, 48))
    # the file: camera-to-world matrices of the rig in a mirrored world, under a w2c key
    filed = [replace(c, w2c=np.linalg.inv(c.w2c @ MIRROR_X)) for c in truth]
    with contextlib.redirect_stderr(io.StringIO()):
        read, mirror = proper_world(filed, Path("m"))
    for c, t in zip(read, truth):
        np.testing.assert_allclose(inverted_reading(c, mirror).w2c, t.w2c, atol=1e-12)
    for t in truth:  # without a mirror: a plain inverse, and reading twice gives the matrix back
        np.testing.assert_allclose(inverted_reading(t, None).w2c, np.linalg.inv(t.w2c), atol=1e-12)
        np.testing.assert_allclose(inverted_reading(inverted_reading(t, None), None).w2c, t.w2c, atol=1e-12)


@pytest.fixture(scope="module")
def rendered():
    """Frame 0 of a textured synthetic ring, six cameras at 320x240: enough SIFT matches."""
    scene = SynthScene(SynthConfig(frames=1, cameras=6, width=320, height=240, texture_size=256))
    cams = scene.cameras()
    r = MeshRenderer(scene, 320, 240)
    r.set_frame(0)
    frames = [r.render(c) for c in cams]
    r.release()
    return cams, frames


def _check(cams, frames, tmp_path, mirror=None, by_layout=True):
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        out = check_poses(cams, frames, mirror, Path("meta.json"), tmp_path / "work", PoseCheckConfig(), ColmapOptions(),
                          by_layout=by_layout)
    return out, err.getvalue()


def test_rendered_frames_agree_with_true_poses_and_read_camera_to_world_files(rendered, tmp_path) -> None:
    cams, frames = rendered
    out, said = _check(cams, frames, tmp_path)
    assert out is cams and "poses agree with the images" in said
    agree = float(said.split("images: ")[1].split("%")[0])
    assert agree >= 90
    filed = [replace(c, w2c=np.linalg.inv(c.w2c)) for c in cams]  # camera-to-world under the w2c key
    out, said = _check(filed, frames, tmp_path)
    assert "reading them as camera-to-world" in said and said.count("\n") == 1
    for o, c in zip(out, cams):
        np.testing.assert_allclose(o.w2c, c.w2c, atol=1e-9)


def test_a_held_out_camera_takes_no_part(rendered, tmp_path) -> None:
    """Its frame is not given and its pose, however wrong, changes nothing of the decision."""
    cams, frames = rendered
    filed = [replace(c, w2c=np.linalg.inv(c.w2c)) for c in cams]
    held = [None] + frames[1:]
    out_a, _ = _check(filed, held, tmp_path)
    moved = [replace(filed[0], w2c=look_at(np.array([9.0, -3.0, 5.0]), np.ones(3)))] + filed[1:]
    out_b, _ = _check(moved, held, tmp_path)
    for a, b, c in zip(out_a[1:], out_b[1:], cams[1:]):
        assert np.array_equal(a.w2c, b.w2c)
        np.testing.assert_allclose(a.w2c, c.w2c, atol=1e-9)


def test_poses_that_belong_to_other_images_are_kept_with_a_warning(rendered, tmp_path) -> None:
    """Each camera turned by 5 degrees about a random axis: the matches leave their lines (a
    camera order shifted along the symmetric ring would not do: the rig would only turn whole)."""
    cams, frames = rendered
    rng = np.random.default_rng(4)
    turned = []
    for c in cams:
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        a, k = np.radians(5.0), np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        T = np.eye(4)
        T[:3, :3] = np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k
        turned.append(replace(c, w2c=T @ c.w2c))
    out, said = _check(turned, frames, tmp_path)
    assert out is turned and said.startswith("warning: meta.json: only ") and "check that the calibration" in said


def _wide_rig(n: int = 3) -> list[Camera]:
    """``n`` cameras around a point away from the world's origin, as a room's calibration puts
    them (around the origin both readings of a symmetric ring look inwards: only SIFT can tell)."""
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    centre = np.array([2.0, -1.0, 0.5])
    return [Camera(str(i + 1), 320, 240, K, look_at(centre + np.array([4 * np.cos(a), 4 * np.sin(a), 1.3]), centre))
            for i, a in enumerate(np.linspace(0, 2 * np.pi, n, endpoint=False))]


def test_a_wide_rig_without_matches_is_read_by_where_it_looks(tmp_path) -> None:
    """Three cameras 120 degrees apart on noise frames: no matches to judge by. Read as given,
    camera-to-world matrices make the rig look away from itself; read inverted it looks at one
    point: that reading is taken, for a layout written by hand. True poses stay as they are."""
    truth = _wide_rig()
    rng = np.random.default_rng(0)
    noise = [rng.integers(0, 255, (240, 320, 3)).astype(np.uint8) for _ in truth]
    out, said = _check(truth, noise, tmp_path)
    assert out is truth and "too few to check" in said
    filed = [replace(c, w2c=np.linalg.inv(c.w2c @ MIRROR_X)) for c in truth]
    with contextlib.redirect_stderr(io.StringIO()):
        read, mirror = proper_world(filed, Path("m"))
    out, said = _check(read, noise, tmp_path, mirror)
    assert "look away from one another" in said and "too few feature matches to tell: 0" in said
    for o, c in zip(out, truth):
        np.testing.assert_allclose(o.w2c, c.w2c, atol=1e-9)
    # a format written by a program (COLMAP, LLFF) is not second-guessed by the layout rule
    out, said = _check(read, noise, tmp_path, mirror, by_layout=False)
    assert out is read and "too few to check" in said


def _write_hfu_shaped(root: Path, truth: list[Camera], frames: int = 3) -> None:
    """The shape of a public 3-camera Dynamic 3D Gaussians capture: ids 1..3, train_meta.json
    only, ims/<id>/NNNNN.jpg (one image more per camera than the meta lists), 1-bit masks for
    every camera, camera-to-world matrices of a mirrored world under ``w2c``, no point cloud."""
    rng = np.random.default_rng(2)
    for c in truth:
        for t in range(frames + 1):
            (root / "ims" / c.name).mkdir(parents=True, exist_ok=True)
            (root / "seg" / c.name).mkdir(parents=True, exist_ok=True)
            img = rng.integers(0, 255, (c.height, c.width, 3)).astype(np.uint8)
            Image.fromarray(img).save(root / "ims" / c.name / f"{t:05d}.jpg", quality=90)
            m = np.zeros((c.height, c.width), bool)
            m[60:180, 120:200] = True
            Image.fromarray(m).save(root / "seg" / c.name / f"{t:05d}.png")  # mode "1"
    filed = [np.linalg.inv(c.w2c @ MIRROR_X).tolist() for c in truth]
    md = {"w": 320, "h": 240, "k": [[c.K.tolist() for c in truth] for _ in range(frames)],
          "w2c": [filed for _ in range(frames)], "fn": [[f"{c.name}/{t:05d}.jpg" for c in truth] for t in range(frames)],
          "cam_id": [[int(c.name) for c in truth] for _ in range(frames)]}
    (root / "train_meta.json").write_text(json.dumps(md))


def test_a_public_three_camera_capture_prepares_with_its_true_poses(tmp_path) -> None:
    truth = _wide_rig()
    _write_hfu_shaped(tmp_path / "src", truth)
    src = open_source(tmp_path / "src")
    assert src.camera_names == ["1", "2", "3"] and src.default_test == ["1"] and src.num_frames == [3] * 3
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        s = PreparedScene.load(prepare(PrepareConfig(src=tmp_path / "src", out=tmp_path / "out", **FAST)))
    said = err.getvalue()
    assert "every camera's rotation is mirrored" in said and "reading them as camera-to-world" in said
    assert s.test_cameras == ["1"] and s.num_frames == 3 and s.mask_cameras == ["2", "3"]
    for c, t in zip(s.cameras, truth):
        np.testing.assert_allclose(c.K, t.K, atol=1e-9)
        np.testing.assert_allclose(c.w2c, t.w2c, atol=1e-6)
    assert s.source["world_mirrored"] == "x" and s.source["poses_read_as"] == "camera-to-world"
    with contextlib.redirect_stderr(io.StringIO()):
        kept = PreparedScene.load(prepare(PrepareConfig(src=tmp_path / "src", out=tmp_path / "as-given",
                                                        check_poses=False, **FAST)))
    assert "poses_read_as" not in kept.source
    for c, t in zip(kept.cameras, truth):  # as given: the mirrored file's matrices, mirrored back
        assert not np.allclose(c.w2c, t.w2c, atol=1e-3)


def test_hint_points_of_a_mirrored_world_give_the_same_depths(tmp_path) -> None:
    """init_pt_cld.npz lives in the file's world: mirrored with the cameras, each camera's depth
    hints are those of the unmirrored capture."""
    truth = ring_cameras(4, size=(64, 48), radius=4.0)
    xyz = np.random.default_rng(3).normal(size=(400, 3)) * 0.4
    hints = []
    for mirrored in (False, True):
        root = tmp_path / str(mirrored)
        F = MIRROR_X if mirrored else np.eye(4)
        cams = [replace(c, name=str(i), w2c=c.w2c @ F) for i, c in enumerate(truth)]
        for c in cams:
            (root / "ims" / c.name).mkdir(parents=True)
            Image.new("RGB", (64, 48)).save(root / "ims" / c.name / "000000.jpg")
        md = {"w": 64, "h": 48, "k": [[c.K.tolist() for c in cams]], "w2c": [[c.w2c.tolist() for c in cams]],
              "fn": [[f"{c.name}/000000.jpg" for c in cams]], "cam_id": [[int(c.name) for c in cams]]}
        (root / "train_meta.json").write_text(json.dumps(md))
        pts = xyz @ F[:3, :3].T
        np.savez(root / "init_pt_cld.npz", data=np.concatenate([pts, np.ones((400, 4))], 1))
        with contextlib.redirect_stderr(io.StringIO()):
            hints.append(open_source(root).extra["near_far"])
    assert all(h is not None for h in hints[0])
    np.testing.assert_allclose(np.array(hints[1]), np.array(hints[0]), rtol=1e-9)
