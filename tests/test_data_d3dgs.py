"""The Dynamic 3D Gaussians layout (train_meta.json / test_meta.json + ims/ + seg/) through
atgs-prepare, its foreground masks in the prepared scene, and its bad inputs.

The capture is rendered by the mesh renderer; the masks come from its true depth. A second
capture has the shape of the published CMU Panoptic sequences (written here, not by
write_d3dgs): 31 numeric cameras, 0, 10, 15 and 30 held out, masks for the training cameras only,
init_pt_cld.npz; and the COLMAP ids are checked to follow image names, not positions."""

from __future__ import annotations

import contextlib
import io
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
from atgs.data.motion_measure import box_downsample
from atgs.data.moving_points import MotionPointsConfig, background, motion_keyframes, motion_mask, motion_points
from atgs.data.mvs import StereoConfig
from atgs.data.prepare import PrepareConfig, _mask_cameras, prepare
from atgs.data.scene import MemoryScene, PreparedScene, read_mask, read_rgb, write_prepared_scene
from atgs.data.sources import detect_format, open_source
from atgs.data.synth.mesh_renderer import MeshRenderer
from atgs.data.synth.scene import SynthConfig, SynthScene
from atgs.timeline import evenly_spaced
from builders import ring_cameras

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
    # held-out cameras' masks are never read: only the training cameras' are kept
    assert s.mask_cameras == ["1", "10", "12"] and s.has_masks
    assert json.loads((capture["prepared"] / "scene.json").read_text())["masks"] == ["1", "10", "12"]
    assert not (capture["prepared"] / "masks" / "4").exists()
    for ci, cam in enumerate(s.cameras):
        want = capture["cams"][cam.name].scaled(0.5)
        assert (cam.width, cam.height) == (W // 2, H // 2)
        np.testing.assert_allclose(cam.K, want.K, atol=1e-6)
        np.testing.assert_allclose(cam.w2c, want.w2c, atol=1e-6)
        for f in range(FRAMES):
            full = capture["masks"][cam.name, f]
            assert 0.02 < full.mean() < 0.9  # both classes present
            share = full.reshape(H // 2, 2, W // 2, 2).mean(axis=(1, 3))  # independent 2x2 box filter
            if cam.name in TEST:
                assert not s.has_mask(ci)
                with pytest.raises(DataError, match=f"camera {cam.name} has no masks"):
                    s.mask(ci, f)
            else:
                assert s.has_mask(ci) and np.array_equal(s.mask(ci, f), share >= 0.5), (cam.name, f)
            with Image.open(capture["src"] / "ims" / cam.name / f"{f:06d}.jpg") as im:
                frame = np.asarray(im.convert("RGB").resize((W // 2, H // 2), Image.BOX))
            assert np.array_equal(s.image_uint8(ci, f), frame)
    on_disk = np.asarray(Image.open(capture["prepared"] / "masks" / "10" / "000002.png"))
    assert on_disk.dtype == np.uint8 and set(np.unique(on_disk)) <= {0, 255}


def test_motion_points_take_the_captures_foreground_masks(capture, tmp_path) -> None:
    """Where a training camera has masks, its motion masks are the capture's (box-averaged to
    their working resolution), not the frames' difference; a training camera without masks
    (camera 12 here) prepares without, with one line naming it, and its motion masks are its
    frames' difference from their background: the moving share reported mixes the two."""
    src = tmp_path / "src"
    shutil.copytree(capture["src"], src)
    shutil.rmtree(src / "seg" / "12")
    cfg = MotionPointsConfig(per_interval=2, long_side=24, min_views=2, min_points=1, resolution=16, subdivide=2)
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        s = PreparedScene.load(prepare(PrepareConfig(src=src, out=tmp_path / "p", downscale=2.0,
                                                     **{**FAST, "motion": cfg})))
    notes = [line for line in err.getvalue().splitlines() if "have no masks" in line]
    assert len(notes) == 1 and "camera(s) 12 have no masks" in notes[0]
    assert s.mask_cameras == ["1", "10"] and not (tmp_path / "p" / "masks" / "12").exists()
    stats = json.loads((tmp_path / "p" / "scene.json").read_text())["motion_points"]
    frames = motion_keyframes(FRAMES, 1, 2)  # prepared at 48x36, masks at 24x18: 2x2 blocks
    small = lambda f: box_downsample(s.image_uint8(3, f), cfg.long_side)  # noqa: E731 - camera 12
    bg = background([small(f) for f in evenly_spaced(FRAMES, cfg.background_frames)])
    share = np.mean([[(s.mask(i, f).reshape(H // 4, 2, W // 4, 2).mean(axis=(1, 3)) >= 0.5).mean()
                      for i in (0, 2)] + [motion_mask(small(f), bg, cfg).mean()] for f in frames])
    assert stats["moving_fraction"] == pytest.approx(share, abs=1e-4) and sum(stats["points"]) > 0


def test_motion_points_mix_masked_and_unmasked_cameras() -> None:
    """mask_of returns None for a camera without masks: that camera alone reads background frames
    and takes its frames' difference (none here: the frames stand still), the others their masks."""
    cams, F = ring_cameras(5, size=(32, 24), radius=4.0, height=1.0), 9
    rng = np.random.default_rng(3)
    frames = [rng.integers(0, 255, (c.height, c.width, 3)).astype(np.uint8) for c in cams]
    masks = []
    for k in range(len(cams)):
        m = np.zeros((24, 32), bool)
        m[8:16, 12 + k:20 + k] = True
        masks.append(m)
    reads = [0] * len(cams)

    def frame_of(ci: int, f: int) -> np.ndarray:
        reads[ci] += 1
        return frames[ci]

    kfs, box = motion_keyframes(F, 1, 2), np.array([[-1.5] * 3, [1.5] * 3])
    cfg = MotionPointsConfig(resolution=8, subdivide=2, long_side=32, select="surface", min_views=2, min_points=1)
    mp = motion_points(frame_of, cams, F, kfs, box, cfg, progress=False,
                       mask_of=lambda ci, f: None if ci == 2 else masks[ci])
    shares = [m.mean() for m in masks]
    shares[2] = 0.0  # still frames: no difference from the background
    assert mp.stats["moving_fraction"] == pytest.approx(np.mean(shares), abs=1e-4)
    n_bg = len(evenly_spaced(F, cfg.background_frames))
    assert reads == [len(kfs) + (n_bg if ci == 2 else 0) for ci in range(len(cams))]


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
    with pytest.raises(DataError, match=r"masks/1/000000.png: not found but scene.json says camera 1 has masks"):
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
                     r"seg/12/000002.png: not found, but camera 12 has masks of other frames; add the missing "
                     r"masks, or remove .*seg/12 to prepare the camera without masks"),
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


def test_scene_json_records_the_cameras_with_masks(tmp_path) -> None:
    """"masks" lists the cameras with masks (true, in older scenes: all of them)."""
    cams = [Camera(f"c{i}", 8, 6, np.diag([8.0, 8.0, 1.0]), look_at(np.array([3.0, i, 1.0]), np.zeros(3)))
            for i in range(3)]
    out = write_prepared_scene(tmp_path / "s", MemoryScene(cams, 1), lambda c, f: np.zeros((6, 8, 3)))
    for name in ("c0", "c2"):
        _save_mask(out / "masks" / name / "000000.png", np.eye(6, 8, dtype=bool))
    meta_path = out / "scene.json"
    meta = json.loads(meta_path.read_text())

    def load(masks) -> PreparedScene:
        meta_path.write_text(json.dumps({**meta, "masks": masks}))
        return PreparedScene.load(out)

    s = load(["c2", "c0"])
    assert s.mask_cameras == ["c0", "c2"] and [s.has_mask(i) for i in range(3)] == [True, False, True]
    assert np.array_equal(s.mask(2, 0), np.eye(6, 8, dtype=bool))
    with pytest.raises(DataError, match=r"scene.json: camera c1 has no masks \(.*cameras with masks: c0, c2\)"):
        s.mask(1, 0)
    with pytest.raises(DataError, match=r"masks/c1/000000.png: not found but scene.json says camera c1 has masks"):
        load(True)  # an older scene: every camera
    _save_mask(out / "masks" / "c1" / "000000.png", np.eye(6, 8, dtype=bool))
    assert load(True).mask_cameras == ["c0", "c1", "c2"] and load(False).mask_cameras == []
    for bad, pattern in ((["c9"], "'masks' names camera c9, which is not in 'cameras'"),
                         ("c0", "'masks' must be a list of camera names")):
        with pytest.raises(DataError, match=pattern):
            load(bad)
    # the writer: names (any order) or True, stored in camera order
    from atgs.data.scene import write_scene_metadata
    write_scene_metadata(out, MemoryScene(cams, 1), name="s", masks=["c1", "c0"])
    assert json.loads(meta_path.read_text())["masks"] == ["c0", "c1"]
    write_scene_metadata(out, MemoryScene(cams, 1), name="s", masks=True)
    assert json.loads(meta_path.read_text())["masks"] == ["c0", "c1", "c2"]
    write_scene_metadata(out, MemoryScene(cams, 1), name="s")
    assert "masks" not in json.loads(meta_path.read_text())
    with pytest.raises(ValueError, match="masks names camera 'x'"):
        write_scene_metadata(out, MemoryScene(cams, 1), name="s", masks=["x"])


# --- the published layout: CMU Panoptic as Dynamic 3D Gaussians packages it --------------------

HELD_OUT, UW, UH, UF = [0, 10, 15, 30], 32, 24, 2
UPSTREAM_TRAIN = [i for i in range(31) if i not in HELD_OUT]


def _dome_w2c(i: int) -> np.ndarray:
    a = 2 * np.pi * i / 31
    return look_at(np.array([4 * np.cos(a), 4 * np.sin(a), 1.5 + np.sin(3 * a)]), np.zeros(3))


def _write_upstream(root: Path) -> None:
    """The published shape: ims/<id>/NNNNNN.jpg for ids 0..30, seg/<id>/NNNNNN.png for the 27
    training cameras only, metas with per-timestep lists in ascending cam_id order and fn paths
    "<id>/NNNNNN.jpg", and init_pt_cld.npz (key data: xyz, rgb in 0..1, seg)."""
    rng = np.random.default_rng(0)
    tex = rng.integers(0, 255, (UH, UW, 3)).astype(np.uint8)
    for t in range(UF):
        for i in range(31):
            (root / "ims" / str(i)).mkdir(parents=True, exist_ok=True)
            Image.fromarray(np.roll(tex, i + t, axis=1)).save(root / "ims" / str(i) / f"{t:06d}.jpg", quality=90)
            if i not in HELD_OUT:
                m = np.zeros((UH, UW), bool)
                m[6:18, 10 + t:20 + t] = True
                _save_mask(root / "seg" / str(i) / f"{t:06d}.png", m)
    K = [[28.0, 0.0, 16.0], [0.0, 28.0, 12.0], [0.0, 0.0, 1.0]]
    for name, ids in (("train_meta.json", UPSTREAM_TRAIN), ("test_meta.json", HELD_OUT)):
        md = {"w": UW, "h": UH, "k": [[K for _ in ids] for _ in range(UF)],
              "w2c": [[_dome_w2c(i).tolist() for i in ids] for _ in range(UF)],
              "fn": [[f"{i}/{t:06d}.jpg" for i in ids] for t in range(UF)], "cam_id": [list(ids) for _ in range(UF)]}
        (root / name).write_text(json.dumps(md))
    xyz = rng.normal(size=(500, 3)) * 0.3  # a blob at the centre, 4 units from every camera
    np.savez(root / "init_pt_cld.npz", data=np.concatenate([xyz, rng.random((500, 3)), np.ones((500, 1))], 1))


@pytest.fixture(scope="module")
def upstream(tmp_path_factory):
    root = tmp_path_factory.mktemp("panoptic")
    _write_upstream(root / "src")
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        out = prepare(PrepareConfig(src=root / "src", out=root / "prepared", **FAST))
    return {"src": root / "src", "prepared": out, "stderr": err.getvalue()}


def test_upstream_layout_opens_in_number_order(upstream) -> None:
    src = open_source(upstream["src"])
    assert detect_format(upstream["src"]) == "d3dgs"
    assert src.camera_names == [str(i) for i in range(31)] and src.default_test == ["0", "10", "15", "30"]
    assert src.images[2][1] == upstream["src"] / "ims" / "2" / "000001.jpg"
    for i in range(31):
        np.testing.assert_allclose(src.cameras[i].w2c, _dome_w2c(i), atol=1e-9)
        if i in HELD_OUT:
            assert src.masks[i] is None and not src.camera_has_masks(i, range(UF))
            with pytest.raises(DataError, match=f"camera {i} has no masks"):
                src.mask(i, 0)
        else:
            assert src.camera_has_masks(i, range(UF)) and src.masks[i][1] == upstream["src"] / "seg" / str(i) / "000001.png"
    # init_pt_cld.npz: per-camera depth hints around the distance from each camera to the blob
    assert src.extra["init_points"] == 500 and len(src.extra["near_far"]) == 31
    for cam, (near, far) in zip(src.cameras, src.extra["near_far"]):
        d = np.linalg.norm(cam.center)
        assert d - 1.2 < near < d < far < d + 1.2, (cam.name, d, near, far)


def test_upstream_layout_prepares(upstream) -> None:
    """Both of the published layout's failures are gone: masks for the training cameras only,
    and camera folders whose string order ("10" < "2") is not their number order."""
    s = PreparedScene.load(upstream["prepared"])
    assert s.camera_names == [str(i) for i in range(31)] and s.test_cameras == ["0", "10", "15", "30"]
    assert s.mask_cameras == [str(i) for i in UPSTREAM_TRAIN]
    assert s.mask(2, 1).shape == (UH, UW) and s.mask(2, 1)[12, 16]
    with pytest.raises(DataError, match="camera 15 has no masks"):
        s.mask(15, 0)
    notes = [line for line in upstream["stderr"].splitlines() if line.startswith("note:")]
    assert not any("have no masks" in n for n in notes)  # every training camera has its masks
    init = [n for n in notes if "init_pt_cld.npz" in n]
    assert len(init) == 1 and "500 points, used only as depth-range hints" in init[0]
    assert s.source["init_points"] == 500 and len(s.source["near_far"]) == 31
    assert len(s.points) > 0


def test_upstream_held_out_masks_are_never_read(upstream, tmp_path) -> None:
    """A held-out camera with a partial (or broken) set of masks is fine; a training camera's
    partial set is a one-line error naming the missing file."""
    src = tmp_path / "src"
    shutil.copytree(upstream["src"], src)
    (src / "seg" / "0").mkdir()
    Image.new("L", (3, 3)).save(src / "seg" / "0" / "000000.png")
    s = open_source(src)
    assert s.masks[0] is not None  # it has one mask, the wrong size, of one of two frames
    assert _mask_cameras(s, ["0", "10", "15", "30"], range(UF)) == [str(i) for i in UPSTREAM_TRAIN]
    (src / "seg" / "7" / "000001.png").unlink()
    with pytest.raises(DataError, match=r"seg/7/000001.png: not found, but camera 7 has masks of other frames") as e:
        _mask_cameras(open_source(src), ["0", "10", "15", "30"], range(UF))
    assert "\n" not in str(e.value)
    assert _mask_cameras(open_source(src), ["0", "10", "15", "30"], range(1)) == [str(i) for i in UPSTREAM_TRAIN]


def test_upstream_init_points_are_optional_and_checked(upstream, tmp_path) -> None:
    src = tmp_path / "src"
    shutil.copytree(upstream["src"], src)
    (src / "init_pt_cld.npz").unlink()
    assert "near_far" not in open_source(src).extra and "init_points" not in open_source(src).extra
    np.savez(src / "init_pt_cld.npz", points=np.zeros((4, 7)))
    with pytest.raises(DataError, match=r"init_pt_cld.npz: no array 'data' .*; fix it or remove it"):
        open_source(src)
    np.savez(src / "init_pt_cld.npz", data=np.zeros(7))
    with pytest.raises(DataError, match=r"init_pt_cld.npz: 'data' is a float64 array of shape \(7,\)"):
        open_source(src)
    (src / "init_pt_cld.npz").write_bytes(b"not a zip")
    with pytest.raises(DataError, match=r"init_pt_cld.npz: unreadable") as e:
        open_source(src)
    assert "\n" not in str(e.value)
    # points no camera sees give no hint for any camera
    np.savez(src / "init_pt_cld.npz", data=np.full((100, 7), 50.0))
    assert open_source(src).extra["near_far"] == [None] * 31


def test_colmap_ids_follow_image_names_not_positions(tmp_path) -> None:
    """COLMAP numbers the images of a database in the string order of their names ("10/..." before
    "2/..."); database_ids reads each name's ids back, whatever the caller's order."""
    import pycolmap

    from atgs.data.colmap_ops import database_ids

    names = [f"{c}/000000.png" for c in ("1", "2", "10", "11", "cam_b", "00")]
    rng = np.random.default_rng(1)
    for n in names:
        (tmp_path / "img" / n).parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(rng.integers(0, 255, (24, 32, 3)).astype(np.uint8)).save(tmp_path / "img" / n)
    db_path = tmp_path / "database.db"
    pycolmap.Database.open(db_path).close()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    pycolmap.import_images(db_path, tmp_path / "img", camera_mode=pycolmap.CameraMode.PER_IMAGE, image_names=names,
                           options=reader)
    db = pycolmap.Database.open(db_path)
    truth = {img.name: (img.image_id, img.camera_id) for img in db.read_all_images()}
    db.close()
    ids = database_ids(db_path, names, tmp_path / "img")
    assert ids == [truth[n] for n in names]
    assert ids != [(i + 1, i + 1) for i in range(len(names))]  # positions would be wrong here
    with pytest.raises(DataError, match=r"img/3/000000.png: COLMAP could not read this image"):
        database_ids(db_path, ["3/000000.png"], tmp_path / "img")
