"""PreparedScene reader/builder: layout contract, lazy frames, validation, atomic writes."""

from __future__ import annotations

import json

import numpy as np
import pytest
from plyfile import PlyData

from atgs.cameras import Camera, look_at
from atgs.data.errors import DataError
from atgs.errors import OutputError
from atgs.data.point_cloud import PlyPointCloud
from atgs.data.scene import MemoryScene, PreparedScene, write_prepared_scene

K = np.array([[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]])


def _cams(n: int = 3) -> list[Camera]:
    return [Camera(f"cam{i:02d}", 32, 24, K, look_at(np.array([3 * np.cos(i), 3 * np.sin(i), 1.0]), np.zeros(3)))
            for i in range(n)]


def _frame(ci: int, f: int) -> np.ndarray:
    img = np.zeros((24, 32, 3), np.uint8)
    img[..., 0] = ci * 40
    img[..., 1] = f * 10
    img[3, 5, 2] = 200
    return img


def _write(path, **kw):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(30, 3))
    cols = rng.random((30, 3)).astype(np.float32)
    kf = np.arange(30) % 2
    content = dict(fps=25.0, keyframes=[0, 4], test_cameras=["cam01"])
    content.update({k: v for k, v in kw.items() if k in ("fps", "keyframes", "test_cameras")})
    scene = MemoryScene(_cams(), 5, points=pts, point_keyframes=kf, point_colors=cols, **content)
    args = {k: v for k, v in kw.items() if k not in content}
    return write_prepared_scene(path, scene, _frame, **args), pts, cols, kf


def test_layout_and_reader(tmp_path) -> None:
    out, pts, cols, kf = _write(tmp_path / "s")
    meta = json.loads((out / "scene.json").read_text())
    assert meta["format"] == "atgs-scene" and meta["version"] == 1
    assert sorted(meta) == sorted(["format", "version", "name", "fps", "num_frames", "cameras", "test_cameras",
                                   "keyframes", "bounds", "source"])
    assert (out / "images" / "cam02" / "000004.png").is_file()
    ply = PlyData.read(str(out / "points.ply"))["vertex"]
    assert [p.name for p in ply.properties] == ["x", "y", "z", "red", "green", "blue", "keyframe"]

    s = PreparedScene.load(out)
    assert s.num_frames == 5 and s.fps == 25.0 and s.keyframes == [0, 4]
    assert s.train_indices == [0, 2] and s.test_indices == [1]
    assert s.bounds.shape == (2, 3) and np.all(s.bounds[0] < s.bounds[1])
    order = np.argsort(kf, kind="stable")  # the file holds each keyframe's rows together
    np.testing.assert_allclose(s.points, pts[order].astype(np.float32))
    np.testing.assert_allclose(s.point_colors, np.round(cols[order] * 255) / 255, atol=1e-6)
    assert s.point_keyframes.dtype == np.int64 and np.array_equal(s.point_keyframes, kf[order])
    assert isinstance(s.point_cloud, PlyPointCloud)
    for k in (0, 1):
        np.testing.assert_array_equal(s.point_cloud.read(k), pts[kf == k].astype(np.float32))
    img = s.image(2, 3)
    assert img.dtype == np.float32 and img.shape == (24, 32, 3)
    np.testing.assert_allclose(img * 255, _frame(2, 3), atol=1e-4)
    for c, d in zip(s.cameras, _cams()):
        np.testing.assert_allclose(c.w2c, d.w2c)
        assert c.dist is None


def test_refuses_to_overwrite_and_keeps_old_scene(tmp_path) -> None:
    out, *_ = _write(tmp_path / "s")
    before = (out / "scene.json").read_text()
    with pytest.raises(OutputError, match="already exists"):
        _write(tmp_path / "s")
    with pytest.raises(RuntimeError):  # a failing frame source in the middle of a rewrite

        def bad(ci: int, f: int) -> np.ndarray:
            if f == 3:
                raise RuntimeError("boom")
            return _frame(ci, f)

        write_prepared_scene(out, MemoryScene(_cams(), 5), bad, overwrite=True)
    assert (out / "scene.json").read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]  # no temp dirs left behind
    _write(tmp_path / "s", fps=50.0, overwrite=True)
    assert PreparedScene.load(out).fps == 50.0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]


@pytest.mark.parametrize("damage, match", [
    (lambda d: (d / "scene.json").unlink(), "scene.json: not found"),
    (lambda d: (d / "scene.json").write_text("{"), "scene.json: unreadable JSON"),
    (lambda d: (d / "points.ply").unlink(), "points.ply: not found"),
    (lambda d: (d / "points.ply").write_bytes(b"ply\nformat binary"), "points.ply: unreadable"),
    (lambda d: (d / "images" / "cam00" / "000000.png").unlink(), "000000.png: first frame of camera cam00"),
])
def test_damaged_scene_errors_name_the_file(tmp_path, damage, match) -> None:
    out, *_ = _write(tmp_path / "s")
    damage(out)
    with pytest.raises(DataError, match=match):
        PreparedScene.load(out)


def test_bad_metadata_and_missing_frame(tmp_path) -> None:
    out, *_ = _write(tmp_path / "s")
    meta = json.loads((out / "scene.json").read_text())
    (out / "images" / "cam01" / "000002.png").unlink()
    with pytest.raises(DataError, match="cam01/000002.png: frame file missing"):
        PreparedScene.load(out).image(1, 2)
    meta["keyframes"] = [4, 0]
    (out / "scene.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match="keyframes"):
        PreparedScene.load(out)
    meta["keyframes"] = [0]  # points refer to keyframe 1, which no longer exists
    (out / "scene.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match="keyframe index out of range"):
        PreparedScene.load(out)


def test_jpg_frames(tmp_path) -> None:
    out, *_ = _write(tmp_path / "s", image_ext=".jpg")
    s = PreparedScene.load(out)
    assert s.image_ext == ".jpg" and (out / "images" / "cam00" / "000000.jpg").is_file()
    assert np.abs(s.image(1, 2) * 255 - _frame(1, 2)).mean() < 3.0


def _scene_reads() -> set[str]:
    """Every attribute atgs/train/ reads of the scene it trains on (``scene.x``, ``self.scene.x``)."""
    import ast
    from pathlib import Path

    import atgs.train

    names = set()
    for path in Path(atgs.train.__file__).parent.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Attribute):
                v = node.value
                if (isinstance(v, ast.Name) and v.id == "scene") or \
                        (isinstance(v, ast.Attribute) and v.attr == "scene" and isinstance(v.value, ast.Name)):
                    names.add(node.attr)
    return names


def test_both_scene_kinds_provide_what_the_trainer_reads(tmp_path) -> None:
    """SceneData names everything atgs/train/ reads of a scene, and PreparedScene and
    MemoryScene both have all of it, with the same meaning."""
    from atgs.train.trainer import SceneData

    members = {n for n in SceneData.__annotations__} | {
        n for n, v in vars(SceneData).items() if not n.startswith("_") and (callable(v) or isinstance(v, property))}
    assert _scene_reads() <= members, f"read but not in SceneData: {_scene_reads() - members}"
    root, pts, cols, kf = _write(tmp_path / "s")
    prepared = PreparedScene.load(root)
    memory = MemoryScene(_cams(), 5, 25.0, [0, 4], pts, kf, ["cam01"],
                         {(c, f): _frame(c, f) for c in range(3) for f in range(5)}, point_colors=cols)
    for scene in (prepared, memory):
        missing = [n for n in members if not hasattr(scene, n)]
        assert not missing, f"{type(scene).__name__} lacks {missing}"
        assert scene.measured_points.dtype == bool and scene.measured_points.shape == (len(scene.points),)
        assert scene.train_indices == [0, 2] and scene.test_indices == [1]
        np.testing.assert_array_equal(scene.image_uint8(2, 3), _frame(2, 3))
        assert len(scene.motion_points) == len(scene.motion_point_keyframes) == 0 and scene.motion_keyframes == []
    assert memory.bounds is None and prepared.bounds.shape == (2, 3)
