"""Unposed input: pycolmap SfM on the first frame recovers the static camera poses.

Ground truth: the synthetic rig (front-facing arc of cameras, like an N3DV capture) rendered by
the independent mesh renderer; poses compared after a similarity (Umeyama) alignment."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from atgs.data.align import pose_errors, umeyama
from atgs.data.mvs import FillConfig, StereoConfig
from atgs.data.prepare import PrepareConfig, prepare
from atgs.data.scene import PreparedScene
from atgs.data.synth.videos import synthesize
from atgs.data.synth.scene import SynthConfig, SynthScene, distance_to_surfaces, sample_surface
from atgs.data.video import iter_frames


def test_umeyama_recovers_a_similarity() -> None:
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    dst = 2.5 * src @ R.T + np.array([1.0, -2.0, 0.5])
    s, R2, t = umeyama(src, dst)
    assert s == pytest.approx(2.5) and np.allclose(R2, R) and np.allclose(t, [1.0, -2.0, 0.5])


CFG = SynthConfig(frames=2, cameras=10, width=320, height=240, arc_deg=90.0, seed=2, preset="small-motion")


@pytest.fixture(scope="module")
def unposed(tmp_path_factory):
    raw = synthesize(tmp_path_factory.mktemp("sfm") / "raw", CFG, progress=False)
    (raw / "poses_bounds.npy").unlink()  # now it is just a folder of videos
    return raw, SynthScene(CFG)


@pytest.mark.parametrize("layout", ["videos", "images"])
def test_sfm_recovers_poses_from_unposed_input(tmp_path, unposed, layout) -> None:
    cfg = CFG
    raw, gt = unposed
    if layout == "images":  # <cam>/<frame>.png folders instead of videos
        src = tmp_path / "imgs"
        for v in sorted(raw.glob("*.mp4")):
            (src / v.stem).mkdir(parents=True)
            for i, img in iter_frames(v):
                Image.fromarray(img).save(src / v.stem / f"{i:04d}.png")
    else:
        src = raw
    # stereo and fill off: this tests the SfM poses and their SIFT points (tests/test_data_mvs.py: the rest)
    out = prepare(PrepareConfig(src=src, out=tmp_path / "p", keyframes=1, frames="0:1", progress=False,
                                stereo=StereoConfig(enabled=False), fill=FillConfig(enabled=False)))
    s = PreparedScene.load(out)
    assert s.source["format"] == layout
    truth = gt.cameras()
    rot, pos = pose_errors(s.cameras, truth)
    size = cfg.scene_size
    assert rot.max() < 1.0, rot
    assert pos.max() < 0.01 * size, pos / size
    # the SfM-posed scene also triangulates onto the true surfaces (after the same alignment)
    sc, R, t = umeyama(np.array([c.center for c in s.cameras]), np.array([c.center for c in truth]))
    pts = sc * s.points[:: max(1, len(s.points) // 300)].astype(np.float64) @ R.T + t
    d = distance_to_surfaces(gt, 0, pts)
    # far backdrop points inherit the ~1% focal-length uncertainty of single-frame SfM
    assert len(pts) > 100 and np.median(d) < 0.02 * size, np.median(d) / size
    print("sfm rot max %.3f deg, pos max %.4f of scene size, points median %.4f of scene size, timings %s"
          % (rot.max(), pos.max() / size, np.median(d) / size, s.source["timings_s"]))
    # sanity of the error measure itself: exact surface samples are at distance ~0
    assert distance_to_surfaces(gt, 0, sample_surface(gt, 0, 50)).max() < 1e-9


def test_known_pose_triangulation_gives_the_same_points_on_any_thread_count(tmp_path, unposed) -> None:
    """COLMAP verifies each image pair with a RANSAC; unseeded, it drew from the generator of
    whichever worker thread took the pair, so two runs on the same frames triangulated different
    points (1,106 vs 1,095 on a keyframe of the built-in scene) and every later step of
    atgs-prepare (stereo depth ranges, surface extension, motion points' box) differed with them."""
    from atgs.data.colmap_ops import ColmapOptions, triangulate_known_poses

    raw, gt = unposed
    names = []
    for v in sorted(raw.glob("*.mp4")):
        _, img = next(iter_frames(v))
        (tmp_path / "img").mkdir(exist_ok=True)
        Image.fromarray(img).save(tmp_path / "img" / f"{v.stem}.png")
        names.append(f"{v.stem}.png")
    runs = []
    for k, threads in enumerate((-1, -1, 1)):
        pts, rgb = triangulate_known_poses(tmp_path / "img", names, gt.cameras(), tmp_path / f"w{k}",
                                           ColmapOptions(num_threads=threads))
        order = np.lexsort(np.round(pts, 6).T[::-1])
        runs.append((pts[order], rgb[order]))
    assert len(runs[0][0]) > 200
    for pts, rgb in runs[1:]:
        np.testing.assert_array_equal(pts, runs[0][0])
        np.testing.assert_array_equal(rgb, runs[0][1])


def test_sfm_without_a_model_names_the_capture_and_writes_nothing(tmp_path, capfd) -> None:
    """Two cameras of flat grey images: SfM finds no model. The one-line error names the user's
    folder (not the preparation's temporary copy), --out is not created, and COLMAP's own log
    line for it (glog, written to the process's stderr) does not come before it."""
    from atgs.data.errors import DataError

    src = tmp_path / "flat"
    for cam in ("camA", "camB"):
        (src / cam).mkdir(parents=True)
        Image.fromarray(np.full((96, 128, 3), 128, np.uint8)).save(src / cam / "0000.png")
    out = tmp_path / "p"
    with pytest.raises(DataError) as err:
        prepare(PrepareConfig(src=src, out=out, keyframes=1, progress=False))
    msg = str(err.value)
    assert msg.startswith(f"{src}:") and "structure-from-motion" in msg and "\n" not in msg
    assert ".tmp" not in msg and not out.exists()
    assert "sparse model" not in capfd.readouterr().err


def _first_frames(raw) -> dict[str, np.ndarray]:
    return {v.stem: next(iter(iter_frames(v)))[1] for v in sorted(raw.glob("*.mp4"))}


def _assert_same_cameras(cams, others) -> None:
    assert len(cams) == len(others)
    for a, b in zip(cams, others):
        assert np.array_equal(a.w2c, b.w2c) and np.array_equal(a.K, b.K) and np.array_equal(a.dist, b.dist), a.name


def test_held_out_camera_changes_no_training_camera(tmp_path, unposed) -> None:
    """Nothing about a held-out camera enters training: SfM runs on the training cameras' images
    alone, and the held-out one is registered after, against that model held fixed. So the
    training cameras' poses and (shared) intrinsics are bit-identical whatever the held-out image
    shows, or whether there is one (in one SfM over all cameras, bundle adjustment moved their
    world-to-camera entries by up to 2e-3 and the focal length by 0.1 px when it was noisy), while
    it is still posed about as well as they are."""
    from atgs.data.align import umeyama
    from atgs.data.colmap_ops import ColmapOptions, sfm_static_cameras
    from atgs.data.errors import DataError

    # One thread: COLMAP's threaded bundle adjustment sums in the order its threads finish, so
    # two runs on the same training images differ by ~1e-4 on a busy machine (seen once in CI);
    # bit-identity is then a test of the held-out image alone.
    one = ColmapOptions(num_threads=1)
    raw, gt = unposed
    frames = _first_frames(raw)
    names = list(frames)
    held = names[0]  # cam00, the convention's held-out camera
    noisy = frames[held].astype(np.float64) + np.random.default_rng(0).normal(0, 8, frames[held].shape)
    flat = np.full_like(frames[held], 128)  # nothing to register

    def sfm(tag, held_img):
        d = tmp_path / tag
        d.mkdir()
        for n, img in frames.items():
            Image.fromarray(held_img if n == held else img).save(d / f"{n}.png")
        return sfm_static_cameras(d, [f"{n}.png" for n in names], names, tmp_path / f"w{tag}", one, held_out=[held])

    runs = [sfm("true", frames[held]), sfm("noisy", np.clip(noisy, 0, 255).astype(np.uint8))]
    # ... or whether there is one at all
    alone = sfm_static_cameras(tmp_path / "true", [f"{n}.png" for n in names[1:]], names[1:], tmp_path / "walone", one)
    _assert_same_cameras(alone, runs[0][1:])
    truth = gt.cameras()
    for cams in runs:
        _assert_same_cameras(cams[1:], runs[0][1:])
        assert np.array_equal(cams[0].K, cams[1].K)  # the shared intrinsics, as training fixed them
        # the held-out pose, in the frame fitted on the training cameras alone
        s, R, t = umeyama(np.array([c.center for c in cams[1:]]), np.array([c.center for c in truth[1:]]))
        h, g = cams[0], truth[0]
        rot = np.degrees(np.arccos(np.clip((np.trace(g.R @ R @ h.R.T) - 1) / 2, -1, 1)))
        assert rot < 1.0 and np.linalg.norm(s * R @ h.center + t - g.center) < 0.01 * CFG.scene_size
    with pytest.raises(DataError) as err:
        sfm("flat", flat)
    msg = str(err.value)
    assert f"held-out camera(s) {held} " in msg and "--test-cams" in msg and "\n" not in msg


def test_similarity_of_two_posings_of_the_same_cameras() -> None:
    """The held-out pose is brought back to the training model's frame by the similarity between
    COLMAP's re-normalized copy of the training cameras and pass 1's; two cameras determine it."""
    from atgs.data.colmap_ops import _similarity

    cams = SynthScene(CFG).cameras()[:2]
    s, R = 1.7, np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])  # 90 degrees about z
    t = np.array([0.3, -2.0, 1.0])
    moved = []
    for c in cams:  # the same cameras in the world x' = s R x + t
        w2c = np.eye(4)
        w2c[:3, :3] = c.R @ R.T
        w2c[:3, 3] = s * c.t - c.R @ R.T @ t
        moved.append(type(c)(c.name, c.width, c.height, c.K, w2c))
        assert np.allclose(moved[-1].center, s * R @ c.center + t)
    s2, R2, t2 = _similarity(cams, moved)
    assert s2 == pytest.approx(s) and np.allclose(R2, R) and np.allclose(t2, t)
