"""atgs-synth -> atgs-prepare end to end on a tiny synthetic scene, every input layout, and bad input.

Ground truth comes from the independent mesh renderer and the analytic scene geometry."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from atgs.cli.prepare import main as prepare_main
from atgs.data.errors import DataError
from atgs.errors import OutputError
from layouts import write_colmap_frames_layout, write_easyvolcap_layout
from atgs.data.moving_points import MotionPointsConfig
from atgs.data.mvs import StereoConfig
from atgs.data.prepare import PrepareConfig, parse_frame_range, prepare
from atgs.data.scene import PreparedScene
from atgs.data.synth.videos import load_ground_truth, synthesize
from atgs.data.synth.mesh_renderer import MeshRenderer
from atgs.data.synth.scene import SynthConfig, distance_to_surfaces
from atgs.data.video import iter_frames
from atgs.io.video import VideoWriter

CFG = SynthConfig(frames=6, cameras=12, width=256, height=192, seed=1, preset="large-motion")
# Tests of the formats and the ingest do not need dense stereo (tests/test_data_mvs.py covers it);
# the fixture's prepare runs it at a small working resolution to stay fast.
NO_STEREO = StereoConfig(enabled=False)


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth")
    src = synthesize(root / "raw", CFG, progress=False)
    scene = load_ground_truth(src)
    r = MeshRenderer(scene, CFG.width, CFG.height)
    cams = scene.cameras()
    gt = {}
    for f in range(CFG.frames):
        r.set_frame(f)
        for ci in (0, 3, 7):
            gt[ci, f] = r.render(cams[ci])
    r.release()
    prepared = prepare(PrepareConfig(src=src, out=root / "prepared", keyframes=2, progress=False,
                                     stereo=StereoConfig(long_side=128)))
    return {"root": root, "src": src, "scene": scene, "gt": gt, "cams": cams, "prepared": prepared}


def test_motion_points_lie_on_the_moving_objects(synth) -> None:
    """The motion keyframes contain the geometry ones, and their points sit on what moves."""
    s = PreparedScene.load(synth["prepared"])
    assert set(s.keyframes) <= set(s.motion_keyframes) and len(s.motion_keyframes) > len(s.keyframes)
    scene, size = synth["scene"], synth["scene"].cfg.scene_size
    # 6 frames are 0.2 s: in the middle frames the objects overlap their own median background,
    # so the first and last keyframes are the ones sure to differ from it
    counts = [int((s.motion_point_keyframes == j).sum()) for j in range(len(s.motion_keyframes))]
    assert counts[0] > 50 and counts[-1] > 50, counts
    for j, f in enumerate(s.motion_keyframes):
        pts = s.motion_points[s.motion_point_keyframes == j]
        if len(pts) == 0:
            continue
        d = distance_to_surfaces(scene, f, pts[:: max(1, len(pts) // 200)], moving_only=True)
        assert np.median(d) < 0.03 * size, (f, np.median(d))  # a hull, not a surface: ~1/3 of an object
    meta = json.loads((Path(synth["prepared"]) / "scene.json").read_text())
    assert meta["motion_points"]["keyframes"] == len(s.motion_keyframes) and meta["motion_points"]["moving_fraction"] > 0


def test_synth_videos_are_lossless(synth) -> None:
    frames = dict(iter_frames(synth["src"] / "cam03.mp4"))
    assert sorted(frames) == list(range(CFG.frames))
    for f in range(CFG.frames):
        assert np.array_equal(frames[f], synth["gt"][3, f])


def test_synth_has_motion_and_sidecar(synth) -> None:
    side = json.loads((synth["src"] / "synth.json").read_text())
    assert side["config"]["preset"] == "large-motion" and side["scene_size"] == pytest.approx(2 * CFG.ring_radius)
    a, b = synth["gt"][0, 0].astype(float), synth["gt"][0, CFG.frames - 1].astype(float)
    changed = np.mean(np.abs(a - b).sum(-1) > 30)
    assert 0.02 < changed < 0.6  # objects move; the static backdrop does not


def test_prepared_n3dv_matches_ground_truth(synth) -> None:
    s = PreparedScene.load(synth["prepared"])
    assert s.num_frames == CFG.frames and s.fps == CFG.fps
    assert s.test_cameras == ["cam00"] and s.test_indices == [0] and len(s.train_indices) == 11
    assert s.keyframes == [0, CFG.frames - 1]
    for c, g in zip(s.cameras, synth["cams"]):
        assert c.name == g.name and c.dist is None
        np.testing.assert_allclose(c.w2c, g.w2c, atol=1e-6)
        np.testing.assert_allclose(c.K, g.K, atol=1e-6)
    for (ci, f), img in synth["gt"].items():
        assert np.array_equal(np.round(s.image(ci, f) * 255).astype(np.uint8), img)
    assert (Path(synth["prepared"]) / "synth.json").is_file()


def test_keyframe_points_lie_on_true_surfaces(synth) -> None:
    s = PreparedScene.load(synth["prepared"])
    size = synth["scene"].cfg.scene_size
    for j, f in enumerate(s.keyframes):
        pts = s.points[s.point_keyframes == j]
        assert len(pts) > 100
        d = distance_to_surfaces(synth["scene"], f, pts[:: max(1, len(pts) // 300)])  # subsample: exact distances are slow
        assert np.median(d) < 0.01 * size, (j, np.median(d))
    inside = np.all((s.points >= s.bounds[0]) & (s.points <= s.bounds[1]), axis=1)
    assert inside.mean() > 0.97  # bounds are robust (percentiles): far outliers may fall outside
    meta = json.loads((Path(synth["prepared"]) / "scene.json").read_text())
    counts, cov = meta["keyframe_points"], meta["coverage"]
    assert all(n > 5 * m for n, m in zip(counts["stereo"], counts["sift"])), counts  # stereo is the dense part
    assert set(cov["per_camera"]) == {c.name for c in s.cameras} and set(cov["test_cameras"]) == {"cam00"}
    assert cov["test_cameras"]["cam00"] > 0.5 and cov["mean"] > 0.5, cov


def test_frame_range_downscale_and_test_cams(synth, tmp_path) -> None:
    out = prepare(PrepareConfig(src=synth["src"], out=tmp_path / "p", frames="1:6:2", downscale=2.0,
                                test_cams=("3", "cam07"), keyframes=1, progress=False, stereo=NO_STEREO,
                                motion=MotionPointsConfig(enabled=False)))
    s = PreparedScene.load(out)
    assert s.num_frames == 3 and s.fps == CFG.fps / 2 and s.keyframes == [0]
    # --no-motion-points: no file, no motion keyframes, and scene.json says it was off
    assert not (out / "motion_points.ply").exists() and s.motion_keyframes == [] and len(s.motion_points) == 0
    assert json.loads((out / "scene.json").read_text())["motion_points"] == {"enabled": False}
    assert s.test_cameras == ["cam03", "cam07"]
    c = s.cameras[3]
    assert (c.width, c.height) == (128, 96)
    np.testing.assert_allclose(c.K, synth["cams"][3].scaled(0.5).K)
    want = np.asarray(Image.fromarray(synth["gt"][3, 3]).resize((128, 96), Image.BOX))
    assert np.array_equal(np.round(s.image(3, 1) * 255).astype(np.uint8), want)
    assert s.source["frames"] == [1, 6, 2]


def _gt_frame(synth):
    def fn(ci: int, f: int) -> np.ndarray:
        if (ci, f) in synth["gt"]:
            return synth["gt"][ci, f]
        return np.full((CFG.height, CFG.width, 3), (ci * 20 + f) % 255, np.uint8)
    return fn


@pytest.mark.parametrize("layout", ["colmap-frames", "colmap-frames-model-in-frame", "easyvolcap"])
def test_other_layouts_give_same_scene(synth, tmp_path, layout) -> None:
    src = tmp_path / "src"
    cams = synth["cams"]
    if layout == "easyvolcap":
        write_easyvolcap_layout(src, cams, _gt_frame(synth), 2)
    else:
        write_colmap_frames_layout(src, cams, _gt_frame(synth), 2, model_in_first_frame=layout.endswith("frame"))
    out = prepare(PrepareConfig(src=src, out=tmp_path / "p", keyframes=1, progress=False, stereo=NO_STEREO))
    s = PreparedScene.load(out)
    assert s.source["format"] == layout.replace("-model-in-frame", "")
    assert s.num_frames == 2 and [c.name for c in s.cameras] == [c.name for c in cams]
    for c, g in zip(s.cameras, cams):
        np.testing.assert_allclose(c.w2c, g.w2c, atol=1e-9)
        np.testing.assert_allclose(c.K, g.K, atol=1e-9)
    assert np.array_equal(np.round(s.image(7, 1) * 255).astype(np.uint8), synth["gt"][7, 1])


def test_frame_helpers() -> None:
    assert list(parse_frame_range("2:10:3", None, None, 100)) == [2, 5, 8]
    assert list(parse_frame_range(None, 5, None, 8)) == [5, 6, 7]
    assert list(parse_frame_range(":-2", None, None, 5)) == [0, 1, 2]
    with pytest.raises(DataError, match="--frames"):
        parse_frame_range("a:b", None, None, 10)
    with pytest.raises(DataError, match="empty"):
        parse_frame_range("20:30", None, None, 10)


# --- bad input ------------------------------------------------------------------------------

def _tiny_n3dv(root: Path, counts=(3, 3, 3)) -> Path:
    from atgs.cameras import Camera, look_at
    from atgs.data.camera_formats import cameras_to_poses_bounds

    root.mkdir(parents=True)
    cams = []
    for i, n in enumerate(counts):
        with VideoWriter(root / f"cam{i:02d}.mp4", 32, 24, 30) as w:
            for f in range(n):
                w.write(np.full((24, 32, 3), 40 * i + f, np.uint8))
        K = np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]])
        cams.append(Camera(f"cam{i:02d}", 32, 24, K, look_at(np.array([3.0, i, 1]), np.zeros(3))))
    np.save(root / "poses_bounds.npy", cameras_to_poses_bounds(cams, [0.5, 10]))
    return root


def test_prepared_keyframes_are_the_models(tmp_path) -> None:
    """6 frames, 3 keyframes: j (F-1)/(K-1) = 2.5 is a half; prepare and the model both take frame 3."""
    from atgs.timeline import Timeline

    scene = PreparedScene.load(prepare(PrepareConfig(src=_tiny_n3dv(tmp_path / "src", counts=(6, 6, 6)),
                                                     out=tmp_path / "out", keyframes=3, progress=False)))
    assert scene.keyframes == Timeline(6, 3, 0, 1).keyframe_frames() == [0, 3, 5]


def _existing_output(tmp_path: Path) -> Path:
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("precious")
    return out


def _prep(src, out, **kw):
    return prepare(PrepareConfig(src=src, out=out, keyframes=1, progress=False, **kw))


def test_bad_inputs_give_one_line_errors_naming_the_file(tmp_path) -> None:
    out = _existing_output(tmp_path)
    # poses that do not match the number of videos
    src = _tiny_n3dv(tmp_path / "a")
    np.save(src / "poses_bounds.npy", np.load(src / "poses_bounds.npy")[:2])
    with pytest.raises(DataError, match=r"poses_bounds.npy: 2 poses for 3 videos"):
        _prep(src, out, overwrite=True)
    # corrupt video
    src = _tiny_n3dv(tmp_path / "b")
    (src / "cam01.mp4").write_bytes(b"\x00\x00\x00 this is not a video" * 10)
    with pytest.raises(DataError, match=r"cam01.mp4: "):
        _prep(src, out, overwrite=True)
    # unequal frame counts: error, or trimmed when asked
    src = _tiny_n3dv(tmp_path / "c", counts=(3, 2, 3))
    with pytest.raises(DataError, match=r"cam01.mp4: camera cam01 has 2 frames .*--trim-mismatch"):
        _prep(src, out, overwrite=True)
    # empty folder, missing folder, unknown layout
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match=r"empty: folder is empty"):
        _prep(tmp_path / "empty", out, overwrite=True)
    with pytest.raises(DataError, match=r"nothing: source path does not exist"):
        _prep(tmp_path / "nothing", out, overwrite=True)
    (tmp_path / "odd").mkdir()
    (tmp_path / "odd" / "notes.txt").write_text("x")
    with pytest.raises(DataError, match=r"odd: cannot recognise the layout"):
        _prep(tmp_path / "odd", out, overwrite=True)
    # nothing already written was destroyed, and no temp dirs are left
    assert (out / "keep.txt").read_text() == "precious"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b", "c", "empty", "odd", "out"]


def test_trim_mismatch_and_overwrite_rules(tmp_path, capsys) -> None:
    src = _tiny_n3dv(tmp_path / "c", counts=(3, 2, 3))
    out = _existing_output(tmp_path)
    with pytest.raises(OutputError, match="already exists; pass --overwrite"):
        _prep(src, out, trim_mismatch=True)
    assert (out / "keep.txt").is_file()
    _prep(src, out, trim_mismatch=True, overwrite=True)
    assert "trimming every camera to 2 frames" in capsys.readouterr().err
    s = PreparedScene.load(out)
    assert s.num_frames == 2 and not (out / "keep.txt").exists()
    assert np.allclose(s.image(2, 1) * 255, 81, atol=2)  # camera 2, frame 1: value 40*2+1


def test_truncated_video_is_an_error_not_a_short_scene(tmp_path) -> None:
    src = _tiny_n3dv(tmp_path / "t", counts=(3, 3, 3))
    data = (src / "cam02.mp4").read_bytes()
    (src / "cam02.mp4").write_bytes(data[: len(data) // 2])
    with pytest.raises(DataError, match="cam02.mp4"):
        _prep(src, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_colmap_frames_missing_image_names_the_file(synth, tmp_path) -> None:
    src = write_colmap_frames_layout(tmp_path / "src", synth["cams"][:4], _gt_frame(synth), 2)
    (src / "frame000001" / "images" / "cam02.png").unlink()
    with pytest.raises(DataError, match=r"frame000001/images/cam02.png: camera cam02 has 1 frames"):
        _prep(src, tmp_path / "out")


def test_cli_prints_one_line_and_exits_2(tmp_path, capsys) -> None:
    (tmp_path / "empty").mkdir()
    out = _existing_output(tmp_path)
    code = prepare_main([str(tmp_path / "empty"), "--out", str(out), "--overwrite"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.count("\n") == 0 and err.startswith("atgs-prepare: error: ") and "empty" in err
    assert "Traceback" not in err and (out / "keep.txt").is_file()
    shutil.rmtree(tmp_path / "empty")


def test_ensure_default_scene_is_cached(tmp_path) -> None:
    from atgs.data.synth.videos import ensure_default_scene

    cfg = SynthConfig(frames=2, cameras=4, width=96, height=72, texture_size=128)
    p1 = ensure_default_scene(tmp_path, cfg, keyframes=1, progress=False)
    stamp = (p1 / "scene.json").stat().st_mtime_ns
    p2 = ensure_default_scene(tmp_path, cfg, keyframes=1, progress=False)
    assert p1 == p2 and (p2 / "scene.json").stat().st_mtime_ns == stamp
    s = PreparedScene.load(p2)
    assert s.num_frames == 2 and len(s.cameras) == 4 and s.image(1, 1).shape == (72, 96, 3)
    other = ensure_default_scene(tmp_path, SynthConfig(frames=2, cameras=4, width=96, height=72, texture_size=128,
                                                       seed=5), keyframes=1, progress=False)
    assert other != p1


def _hold_lock(path: str, marker: str, seconds: float) -> None:
    import time

    from atgs.io.atomic import interprocess_lock

    with interprocess_lock(Path(path)):
        Path(marker).write_text("locked")
        time.sleep(seconds)


def test_interprocess_lock_makes_another_process_wait(tmp_path) -> None:
    import multiprocessing as mp
    import time

    from atgs.io.atomic import interprocess_lock

    lock, marker = tmp_path / "x.lock", tmp_path / "held"
    child = mp.get_context("spawn").Process(target=_hold_lock, args=(str(lock), str(marker), 1.5))
    child.start()
    deadline = time.monotonic() + 60
    while not marker.exists() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert marker.exists()
    t0 = time.monotonic()
    with interprocess_lock(lock):
        waited = time.monotonic() - t0
    child.join(timeout=30)
    assert child.exitcode == 0 and waited > 0.5  # the child held it for 1.5 s after the marker
    t0 = time.monotonic()
    with interprocess_lock(lock):  # free now: no wait
        assert time.monotonic() - t0 < 0.5


def _build_default_scene(cache: str, out: str) -> None:
    from atgs.data.synth.videos import ensure_default_scene

    cfg = SynthConfig(frames=2, cameras=4, width=96, height=72, texture_size=128)
    p = ensure_default_scene(Path(cache), cfg, keyframes=1, progress=False)
    Path(out).write_text(f"{p}\n{(p / 'scene.json').stat().st_mtime_ns}")


def test_ensure_default_scene_builds_once_for_concurrent_processes(tmp_path) -> None:
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    outs = [tmp_path / f"out{i}.txt" for i in range(2)]
    procs = [ctx.Process(target=_build_default_scene, args=(str(tmp_path / "cache"), str(o))) for o in outs]
    for p in procs:
        p.start()
    for p in procs:
        p.join(timeout=300)
    assert [p.exitcode for p in procs] == [0, 0]
    (path_a, stamp_a), (path_b, stamp_b) = (o.read_text().split("\n") for o in outs)
    # same entry, built once: the second process found the first one's scene.json, untouched
    assert path_a == path_b and stamp_a == stamp_b
    assert PreparedScene.load(Path(path_a)).num_frames == 2


def test_easyvolcap_missing_files_are_named(synth, tmp_path) -> None:
    src = write_easyvolcap_layout(tmp_path / "ev", synth["cams"][:3], _gt_frame(synth), 1)
    (src / "extri.yml").unlink()
    with pytest.raises(DataError, match=r"extri.yml: not found"):
        _prep(src, tmp_path / "out")
    src = write_easyvolcap_layout(tmp_path / "ev2", synth["cams"][:3], _gt_frame(synth), 1)
    shutil.rmtree(src / "images" / "cam01")
    with pytest.raises(DataError, match=r"images/cam01: image folder missing for camera cam01"):
        _prep(src, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_synth_cli(tmp_path, capsys) -> None:
    from atgs.cli.synth import main as synth_main

    out = tmp_path / "raw"
    args = [str(out), "--frames", "2", "--cameras", "3", "--width", "48", "--height", "32", "--preset", "small-motion"]
    assert synth_main(args) == 0
    assert sorted(p.name for p in out.iterdir()) == ["cam00.mp4", "cam01.mp4", "cam02.mp4", "poses_bounds.npy", "synth.json"]
    assert np.load(out / "poses_bounds.npy").shape == (3, 17)
    capsys.readouterr()
    assert synth_main(args) == 2  # refuses to overwrite
    err = capsys.readouterr().err.strip()
    assert err.startswith("atgs-synth: error: ") and "already exists" in err and err.count("\n") == 0


def test_calibration_at_other_resolution_is_rescaled_or_refused(synth, tmp_path) -> None:
    from dataclasses import replace as dc_replace

    half = lambda ci, f: np.asarray(Image.fromarray(_gt_frame(synth)(ci, f)).resize((128, 96), Image.BOX))  # noqa: E731
    src = write_easyvolcap_layout(tmp_path / "ev", synth["cams"][:4], half, 1)
    s = PreparedScene.load(_prep(src, tmp_path / "p"))
    np.testing.assert_allclose(s.cameras[1].K, synth["cams"][1].scaled(0.5).K)
    squashed = [dc_replace(c, width=256, height=100) for c in synth["cams"][:4]]
    src = write_easyvolcap_layout(tmp_path / "ev2", squashed, half, 1)
    with pytest.raises(DataError, match="different aspect ratio"):
        _prep(src, tmp_path / "p2")


def test_oracle_scene_has_true_surface_points_and_everything_else_equal(synth, tmp_path) -> None:
    from atgs.data.oracle import make_oracle_scene

    out = make_oracle_scene(synth["prepared"], tmp_path / "oracle", StereoConfig(long_side=128))
    a, b = PreparedScene.load(synth["prepared"]), PreparedScene.load(out)
    assert a.keyframes == b.keyframes and a.test_cameras == b.test_cameras and np.array_equal(a.bounds, b.bounds)
    assert [c.to_dict() for c in a.cameras] == [c.to_dict() for c in b.cameras]
    assert np.array_equal(a.image(5, 3), b.image(5, 3))
    size = synth["scene"].cfg.scene_size
    for j, f in enumerate(b.keyframes):
        pts = b.points[b.point_keyframes == j]
        d = distance_to_surfaces(synth["scene"], f, pts[:: max(1, len(pts) // 300)])
        assert len(pts) > 1000 and np.max(d) < 0.01 * size  # voxel averages of exact surface points
    meta = json.loads((out / "scene.json").read_text())
    assert meta["coverage"]["test_cameras"]["cam00"] > 0.9 and meta["source"]["oracle"]["points"] == len(b.points)
