"""points.ply read one keyframe at a time (atgs.data.point_cloud) against plyfile's whole read."""

from __future__ import annotations

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

import atgs.data.point_cloud as point_cloud
from atgs.data.errors import DataError
from atgs.data.point_cloud import PlyPointCloud, read_points_ply
from atgs.data.scene import write_points_ply
from atgs.keyframe_cloud import ArrayPointCloud


def _points(n=200, K=4, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, 3)).astype(np.float32), rng.random((n, 3)), rng.integers(0, K, n)


def _raw_ply(path, pts, cols, kfs, text=False):
    """A PLY in the given row order (write_points_ply groups the rows by keyframe)."""
    v = np.empty(len(pts), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"),
                                  ("blue", "u1"), ("keyframe", "i4")])
    v["x"], v["y"], v["z"] = pts.T
    c = np.round(cols * 255).astype(np.uint8)
    v["red"], v["green"], v["blue"] = c.T
    v["keyframe"] = kfs
    PlyData([PlyElement.describe(v, "vertex")], text=text).write(str(path))


def _check_against_plyfile(cloud, path, K):
    pts, cols, kfs = read_points_ply(path)  # plyfile, the whole file at once
    for k in range(K):
        assert cloud.count(k) == int((kfs == k).sum())
        np.testing.assert_array_equal(cloud.read(k), pts[kfs == k])  # each keyframe in the file's order
    whole = cloud.whole()
    order = np.argsort(kfs, kind="stable")
    np.testing.assert_array_equal(whole[0], pts[order])
    np.testing.assert_allclose(whole[1], cols[order], atol=1e-7)
    np.testing.assert_array_equal(whole[2], kfs[order])


@pytest.mark.parametrize("chunk", [7, 1 << 18])
def test_a_written_cloud_is_read_by_keyframe(tmp_path, monkeypatch, chunk):
    monkeypatch.setattr(point_cloud, "CHUNK_ROWS", chunk)  # runs that cross the chunks of the index pass
    pts, cols, kfs = _points()
    write_points_ply(tmp_path / "p.ply", pts, cols, kfs)
    cloud = PlyPointCloud.open(tmp_path / "p.ply", 4)
    assert isinstance(cloud, PlyPointCloud)
    assert [len(cloud._runs[k]) for k in range(4)] == [1, 1, 1, 1]  # written grouped by keyframe
    _check_against_plyfile(cloud, tmp_path / "p.ply", 4)
    assert cloud.measured_mask([3, 0, 5, 100]).sum() == 3 + 0 + 5 + cloud.count(3)


@pytest.mark.parametrize("text", [False, True])
def test_other_layouts_are_read_the_same(tmp_path, monkeypatch, text):
    """Rows in any order (many runs: held in memory instead) and ASCII files."""
    monkeypatch.setattr(point_cloud, "MAX_RUNS_PER_KEYFRAME", 2)
    pts, cols, kfs = _points(seed=1)
    _raw_ply(tmp_path / "p.ply", pts, cols, kfs, text=text)
    cloud = PlyPointCloud.open(tmp_path / "p.ply", 4)
    assert isinstance(cloud, ArrayPointCloud)
    _check_against_plyfile(cloud, tmp_path / "p.ply", 4)


def test_a_few_runs_per_keyframe_are_read_from_the_file(tmp_path):
    pts, cols, kfs = _points(seed=2)
    kfs = np.repeat([0, 1, 0, 2, 1, 3, 0, 2], 25)  # 8 runs of 4 keyframes
    _raw_ply(tmp_path / "p.ply", pts, cols, kfs)
    cloud = PlyPointCloud.open(tmp_path / "p.ply", 4)
    assert isinstance(cloud, PlyPointCloud) and len(cloud._runs[0]) == 3
    _check_against_plyfile(cloud, tmp_path / "p.ply", 4)


def test_bad_files_name_the_file(tmp_path):
    pts, cols, kfs = _points()
    write_points_ply(tmp_path / "p.ply", pts, cols, kfs)
    with pytest.raises(DataError, match=r"p\.ply: keyframe index out of range \[0, 3\)"):
        PlyPointCloud.open(tmp_path / "p.ply", 3)
    data = (tmp_path / "p.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[:-40])
    with pytest.raises(DataError, match=r"cut\.ply: truncated"):
        PlyPointCloud.open(tmp_path / "cut.ply", 4)
    (tmp_path / "not.ply").write_text("hello\n")
    with pytest.raises(DataError, match=r"not\.ply: not a PLY file"):
        PlyPointCloud.open(tmp_path / "not.ply", 4)
    with pytest.raises(DataError, match=r"missing\.ply: not found"):
        PlyPointCloud.open(tmp_path / "missing.ply", 4)
