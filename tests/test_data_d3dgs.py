"""The Dynamic 3D Gaussians layout (train_meta.json / test_meta.json + ims/ + seg/) through
atgs-prepare, its foreground masks in the prepared scene, and its bad inputs.

The capture is rendered by the mesh renderer; the masks come from its true depth."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from atgs.cameras import Camera, look_at
from atgs.cli.prepare import main as prepare_main
from atgs.data.camera_formats import cameras_from_d3dgs, read_d3dgs_meta, write_d3dgs
from atgs.data.errors import DataError
from atgs.data.moving_points import MotionPointsConfig, motion_keyframes
from atgs.data.mvs import StereoConfig
from atgs.data.prepare import PrepareConfig, prepare
from atgs.data.scene import MemoryScene, PreparedScene, read_mask, write_prepared_scene
from atgs.data.sources import detect_format, open_source
from atgs.data.synth.mesh_renderer import MeshRenderer
from atgs.data.synth.scene import SynthConfig, SynthScene

IDS = [25, 4, 10, 1, 12]  # written out of order; as strings "10" < "4": the reader orders by number
TEST = ["4", "25"]
FRAMES, W, H = 3, 96, 72
FAST = dict(keyframes=1, progress=False, stereo=StereoConfig(enabled=False), motion=MotionPointsConfig(enabled=False))


def _save_mask(path: Path, mask: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.where(mask, 255, 0).astype(np.uint8)).save(path)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("d3dgs")
    src = root / "src"
    scene = SynthScene(SynthConfig(frames=FRAMES, cameras=len(IDS), width=W, height=H, texture_size=128))
    cams = [replace(c, name=str(i)) for c, i in zip(scene.cameras(), IDS)]
    r = MeshRenderer(scene, W, H)
    masks = {}
    for f in range(FRAMES):
        r.set_frame(f)
        for cam in cams:
            (src / "ims" / cam.name).mkdir(parents=True, exist_ok=True)
            Image.fromarray(r.render(cam)).save(src / "ims" / cam.name / f"{f:06d}.jpg", quality=95)
            depth = r.render_depth(cam)
            masks[cam.name, f] = (depth > 0) & (depth < np.linalg.norm(cam.center))  # nearer than the centre
            _save_mask(src / "seg" / cam.name / f"{f:06d}.png", masks[cam.name, f])
    r.release()
    write_d3dgs(src, cams, TEST, FRAMES, ".jpg")
    prepared = prepare(PrepareConfig(src=src, out=root / "prepared", downscale=2.0, **FAST))
    return {"root": root, "src": src, "cams": {c.name: c for c in cams}, "masks": masks, "prepared": prepared}


def test_source_has_the_written_cameras_in_id_order(capture) -> None:
    src = open_source(capture["src"])
    assert detect_format(capture["src"]) == "d3dgs" and src.kind == "d3dgs"
    assert src.camera_names == ["1", "4", "10", "12", "25"] and src.default_test == TEST
    assert src.num_frames == [FRAMES] * 5 and src.fps == 30.0 and src.sizes == [(W, H)] * 5
    for cam in src.cameras:
        want = capture["cams"][cam.name]
        np.testing.assert_allclose(cam.K, want.K, atol=1e-6)
        np.testing.assert_allclose(cam.w2c, want.w2c, atol=1e-6)
    assert src.images[2][1] == capture["src"] / "ims" / "10" / "000001.jpg"
    assert src.masks[2][1] == capture["src"] / "seg" / "10" / "000001.png"


def test_prepared_scene_has_cameras_frames_and_resized_masks(capture) -> None:
    s = PreparedScene.load(capture["prepared"])
    assert s.camera_names == ["1", "4", "10", "12", "25"] and s.test_cameras == TEST
    assert s.num_frames == FRAMES and s.fps == 30.0 and s.source["format"] == "d3dgs"
    assert s.has_masks and json.loads((capture["prepared"] / "scene.json").read_text())["masks"] is True
    for ci, cam in enumerate(s.cameras):
        want = capture["cams"][cam.name].scaled(0.5)
        assert (cam.width, cam.height) == (W // 2, H // 2)
        np.testing.assert_allclose(cam.K, want.K, atol=1e-6)
        np.testing.assert_allclose(cam.w2c, want.w2c, atol=1e-6)
        for f in range(FRAMES):
            full = capture["masks"][cam.name, f]
            assert 0.02 < full.mean() < 0.9  # both classes present
            share = full.reshape(H // 2, 2, W // 2, 2).mean(axis=(1, 3))  # independent 2x2 box filter
            assert np.array_equal(s.mask(ci, f), share >= 0.5), (cam.name, f)
            with Image.open(capture["src"] / "ims" / cam.name / f"{f:06d}.jpg") as im:
                frame = np.asarray(im.convert("RGB").resize((W // 2, H // 2), Image.BOX))
            assert np.array_equal(s.image_uint8(ci, f), frame)
    on_disk = np.asarray(Image.open(capture["prepared"] / "masks" / "10" / "000002.png"))
    assert on_disk.dtype == np.uint8 and set(np.unique(on_disk)) <= {0, 255}


def test_motion_points_take_the_captures_foreground_masks(capture, tmp_path) -> None:
    """With masks, the motion points' masks are the capture's (box-averaged to their working
    resolution), not the frames' difference: the moving share they report is the masks' share."""
    fast = {**FAST, "motion": MotionPointsConfig(per_interval=2, long_side=24, min_views=2, min_points=1)}
    s = PreparedScene.load(prepare(PrepareConfig(src=capture["src"], out=tmp_path / "p", downscale=2.0, **fast)))
    stats = json.loads((tmp_path / "p" / "scene.json").read_text())["motion_points"]
    train = [i for i, c in enumerate(s.cameras) if c.name not in TEST]
    frames = motion_keyframes(FRAMES, 1, 2)  # prepared at 48x36, masks at 24x18: 2x2 blocks
    share = np.mean([[(s.mask(i, f).reshape(H // 4, 2, W // 4, 2).mean(axis=(1, 3)) >= 0.5).mean()
                      for i in train] for f in frames])
    assert stats["moving_fraction"] == pytest.approx(share, abs=1e-4) and sum(stats["points"]) > 0


def test_prepared_mask_errors_name_the_file(capture, tmp_path) -> None:
    copy = tmp_path / "p"
    shutil.copytree(capture["prepared"], copy)
    (copy / "masks" / "12" / "000001.png").unlink()
    s = PreparedScene.load(copy)
    with pytest.raises(DataError, match=r"masks/12/000001.png: mask not found"):
        s.mask(3, 1)
    Image.new("L", (5, 5)).save(copy / "masks" / "12" / "000002.png")
    with pytest.raises(DataError, match=r"masks/12/000002.png: size 5x5 differs from camera 12"):
        s.mask(3, 2)
    shutil.rmtree(copy / "masks")
    with pytest.raises(DataError, match=r"masks/1/000000.png: not found but scene.json says the scene has masks"):
        PreparedScene.load(copy)
    cams = [Camera(f"c{i}", 8, 6, np.diag([8.0, 8.0, 1.0]), look_at(np.array([3.0, i, 1.0]), np.zeros(3)))
            for i in range(2)]
    blank = write_prepared_scene(tmp_path / "plain", MemoryScene(cams, 1), lambda c, f: np.zeros((6, 8, 3)))
    plain = PreparedScene.load(blank)
    assert not plain.has_masks and "masks" not in json.loads((tmp_path / "plain" / "scene.json").read_text())
    with pytest.raises(DataError, match="the scene has no masks"):
        plain.mask(0, 0)


def test_meta_round_trip_is_exact(tmp_path) -> None:
    rng = np.random.default_rng(0)
    cams = []
    for i, cid in enumerate([7, 0, 31]):
        K = np.array([[500 + rng.random(), 0, 320.3 + i], [0, 499.7 - i, 180.1], [0, 0, 1]])
        cams.append(Camera(str(cid), 640, 360, K, look_at(rng.normal(size=3) * 4, rng.normal(size=3) * 0.1)))
    write_d3dgs(tmp_path, cams, ["31"], 4, ".jpg")
    train, test = read_d3dgs_meta(tmp_path / "train_meta.json"), read_d3dgs_meta(tmp_path / "test_meta.json")
    assert train.cam_ids == [0, 7] and test.cam_ids == [31] and train.files[1] == [f"7/{f:06d}.jpg" for f in range(4)]
    got = {c.name: c for c in cameras_from_d3dgs(train) + cameras_from_d3dgs(test)}
    for c in cams:
        assert (got[c.name].width, got[c.name].height) == (640, 360)
        assert np.array_equal(got[c.name].K, c.K) and np.array_equal(got[c.name].w2c, c.w2c)
    with pytest.raises(ValueError, match="not decimal ids"):
        write_d3dgs(tmp_path, [replace(cams[0], name="cam07")], [], 1)
    with pytest.raises(ValueError, match="several sizes"):
        write_d3dgs(tmp_path, [cams[0], replace(cams[1], width=320)], [], 1)


def test_mask_codings(tmp_path) -> None:
    m = np.zeros((4, 6), bool)
    m[1:3, 2:5] = True
    codings = {"l255": Image.fromarray(np.where(m, 255, 0).astype(np.uint8)),
               "l01": Image.fromarray(m.astype(np.uint8)),  # 0/1 as some datasets store them
               "bilevel": Image.fromarray(m),
               "rgb": Image.fromarray(np.repeat(np.where(m, 255, 0).astype(np.uint8)[..., None], 3, axis=2))}
    for name, im in codings.items():
        im.save(tmp_path / f"{name}.png")
        assert np.array_equal(read_mask(tmp_path / f"{name}.png"), m), name
    assert not read_mask(tmp_path / "l255.png").all() and not np.any(read_mask(_blank(tmp_path)))


def _blank(tmp_path: Path) -> Path:
    Image.new("L", (6, 4)).save(tmp_path / "blank.png")
    return tmp_path / "blank.png"


def test_without_test_meta_or_seg(capture, tmp_path) -> None:
    src = tmp_path / "src"
    shutil.copytree(capture["src"], src)
    (src / "test_meta.json").unlink()
    shutil.rmtree(src / "seg")
    s = open_source(src)
    assert s.camera_names == ["1", "10", "12"] and s.default_test == ["1"] and s.masks is None


# --- bad input ------------------------------------------------------------------------------

def _edit_meta(name: str, edit):
    def fn(src: Path) -> None:
        md = json.loads((src / name).read_text())
        edit(md)
        (src / name).write_text(json.dumps(md))
    return fn


def _move(md: dict) -> None:
    md["w2c"][2][1][0][3] += 0.1


def _singular(md: dict) -> None:
    for step in md["w2c"]:
        step[0][0] = [0.0, 0.0, 0.0, 1.0]  # first row of R zero: R not invertible


def _resize_mask(src: Path) -> None:
    Image.new("L", (W // 2, H // 2)).save(src / "seg" / "1" / "000002.png")


BAD = {
    "missing key": (_edit_meta("train_meta.json", lambda md: md.pop("w2c")), r"train_meta.json: missing key 'w2c'"),
    "bad json": (lambda src: (src / "test_meta.json").write_text("{"), r"test_meta.json: not valid JSON"),
    "size not int": (_edit_meta("train_meta.json", lambda md: md.update(w=96.5)), r"'w' and 'h' must be positive"),
    "missing image": (lambda src: (src / "ims" / "10" / "000001.jpg").unlink(),
                      r"ims/10/000001.jpg: not found, but the metas list it"),
    "missing mask": (lambda src: (src / "seg" / "12" / "000002.png").unlink(),
                     r"seg/12/000002.png: not found; seg/ needs a mask for every image"),
    "moving camera": (_edit_meta("train_meta.json", _move), r"train_meta.json: camera \d+ moves \(its w2c at timestep 2"),
    "w2c not 4x4": (_edit_meta("train_meta.json", lambda md: md["w2c"][0][1].pop()),
                    r"train_meta.json: w2c\[0\]\[1\] is not a 4x4 matrix"),
    "k not 3x3": (_edit_meta("test_meta.json", lambda md: md["k"][1].__setitem__(0, [[1, 2], [3, 4]])),
                  r"test_meta.json: k\[1\]\[0\] is not a 3x3 matrix"),
    "not a rotation": (_edit_meta("train_meta.json", _singular), r"train_meta.json: w2c of camera \d+ is not a rigid"),
    "camera twice": (_edit_meta("test_meta.json", lambda md: [ids.__setitem__(0, 1) for ids in md["cam_id"]]),
                     r"test_meta.json: camera 1 is also in train_meta.json"),
    "mask of another size": (_resize_mask, r"seg/1/000002.png: mask is 48x36, its image 96x72"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_input_is_one_line_naming_the_file(capture, tmp_path, case) -> None:
    edit, pattern = BAD[case]
    src = tmp_path / "src"
    shutil.copytree(capture["src"], src)
    edit(src)
    with pytest.raises(DataError, match=pattern) as e:
        prepare(PrepareConfig(src=src, out=tmp_path / "out", **FAST))
    assert "\n" not in str(e.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"]  # no output, no temporary folder


def test_cli_reports_bad_meta_in_one_line(capture, tmp_path, capsys) -> None:
    src = tmp_path / "src"
    shutil.copytree(capture["src"], src)
    _edit_meta("train_meta.json", _move)(src)
    assert prepare_main([str(src), "--out", str(tmp_path / "out"), "--no-stereo"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("atgs-prepare: error: ") and err.count("\n") == 0 and "train_meta.json" in err
    assert not (tmp_path / "out").exists()
