"""Space the measured points prove empty (atgs.geometry.free_space): against a slow per-point reference and
an analytic plane; its users: the fill of atgs-prepare, the measured-point mask of a prepared
scene, and the free-space loss of training."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from builders import ring_cameras
from atgs.data.keyframe_points import _fill
from atgs.data.mvs import FillConfig, StereoConfig
from atgs.data.scene import PreparedScene
from atgs.geometry.free_space import GRID_CELLS, MARGIN, FreeSpace, carve, depth_grids, merged_grids
from atgs.keyframe_cloud import ArrayPointCloud
from atgs.train.losses import free_space_loss


def _reference(X: np.ndarray, points: np.ndarray, cams, margin=MARGIN, cells=GRID_CELLS) -> np.ndarray:
    """Per sample and camera: the nearest point in the sample's image cell, by a loop."""
    out = np.zeros(len(X), bool)
    for cam in cams:
        cell = max(cam.width, cam.height) / cells
        puv, pz = cam.project(points)
        for k, x in enumerate(X):
            uv, z = cam.project(x[None])
            u, v, z = uv[0, 0], uv[0, 1], z[0]
            if not (z > 0 and 0 <= u < cam.width and 0 <= v < cam.height):
                continue
            same = (pz > 0) & (puv[:, 0] >= 0) & (puv[:, 0] < cam.width) & (puv[:, 1] >= 0) & (puv[:, 1] < cam.height) \
                & (puv[:, 0] // cell == u // cell) & (puv[:, 1] // cell == v // cell)
            if same.any() and z < margin * pz[same].min():
                out[k] = True
    return out


def test_empty_space_matches_a_per_point_loop():
    cams = ring_cameras(4, (40, 30), radius=3.0)
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.7, 0.7, (300, 3))
    X = rng.uniform(-2.5, 2.5, (400, 3))
    empty, seen = FreeSpace.of(cams, points, cells=8).test(torch.as_tensor(X))
    assert np.array_equal(empty.numpy(), _reference(X, points, cams, cells=8))
    assert 5 < int(empty.sum()) < 395 and bool(seen.any())


def test_points_read_in_parts_give_the_grids_of_all_of_them():
    """The trainer (of_parts, a keyframe at a time) and the random anchors' set-up (merged_grids
    over workers, in any order) fold parts: exactly the grids of all the points at once."""
    cams = ring_cameras(3, (40, 30), radius=3.0)
    points = np.random.default_rng(2).uniform(-0.7, 0.7, (500, 3))
    whole = FreeSpace.of(cams, points)
    parts = [points[:7], points[7:7], points[7:260], points[260:]]  # one part empty
    by_parts = FreeSpace.of_parts(cams, iter(parts))
    grids = [depth_grids(cams, p) for p in parts[::-1]]  # another order, as workers gather them
    folded = merged_grids(merged_grids(grids[0], grids[1]), merged_grids(grids[2], grids[3]))
    at_once = depth_grids(cams, points)
    for i in range(len(cams)):
        assert np.isfinite(at_once[i]).any() and not np.isfinite(at_once[i]).all()
        assert np.array_equal(folded[i], at_once[i])
        assert torch.equal(by_parts.grids[i], whole.grids[i])
    assert by_parts.cells == whole.cells


def test_a_plane_proves_the_space_in_front_of_it_empty_and_nothing_else():
    cams = ring_cameras(1, (40, 30), radius=5.0, height=0.0)  # at (5, 0, 0) looking at the origin
    g = np.linspace(-3, 3, 60)
    Y, Z = np.meshgrid(g, g)
    plane = np.stack([np.zeros(Y.size), Y.ravel(), Z.ravel()], 1)  # x = 0: 5 units in front
    fs = FreeSpace.of(cams, plane)
    X = torch.tensor([[3.0, 0.1, 0.1],   # depth 2: empty
                      [0.8, 0.1, 0.1],   # depth 4.2 > 0.8 x 5: not proven empty
                      [-1.0, 0.1, 0.1],  # behind the plane
                      [6.0, 0.0, 0.0]], dtype=torch.float64)  # behind the camera
    empty, seen = fs.test(X)
    assert empty.tolist() == [True, False, False, False] and seen.tolist() == [True, True, True, False]
    assert not FreeSpace.of(cams, np.zeros((0, 3))).test(X)[0].any()  # no points: nothing is empty
    assert carve(X.numpy(), plane, cams).tolist() == [False, True, True, False]


def test_the_fill_never_lands_where_a_camera_sees_a_measured_surface_behind():
    cams = ring_cameras(4, (48, 36), radius=3.0)
    rng = np.random.default_rng(1)
    measured = rng.uniform(-0.5, 0.5, (60, 3)) * [1, 1, 0.05]  # a thin patch: most pixels stay uncovered
    images = [np.full((36, 48, 3), 128, np.uint8)] * 4
    pts, cols = _fill(cams, images, measured, None, StereoConfig(), FillConfig(points=3000), seed=0)
    assert len(pts) > 300 and cols.shape == pts.shape
    assert not FreeSpace.of(cams, measured).test(torch.as_tensor(pts))[0].any()


def test_the_measured_points_of_a_prepared_scene_come_from_its_counts():
    kf = np.array([0] * 7 + [1] * 5)
    scene = PreparedScene(root=None, name="s", fps=1.0, num_frames=2, cameras=ring_cameras(2), test_cameras=[],
                          keyframes=[0, 1], bounds=np.zeros((2, 3)),
                          point_cloud=ArrayPointCloud(np.zeros((12, 3), np.float32), kf, 2),
                          point_counts={"sift": [1, 1], "stereo": [2, 0], "fill": [3, 4], "extend": [1, 0]})
    assert scene.measured_points.tolist() == [True] * 3 + [False] * 4 + [True] + [False] * 4
    scene.point_counts = {"sift": [1, 1], "stereo": [2, 0], "fill": [3, 9], "extend": [1, 0]}  # disagrees
    assert scene.measured_points.all()
    scene.point_counts = {}
    assert scene.measured_points.all()


def test_free_space_loss_pushes_only_the_gaussians_in_empty_space():
    cams = ring_cameras(1, (40, 30), radius=5.0, height=0.0)
    g = np.linspace(-3, 3, 60)
    Y, Z = np.meshgrid(g, g)
    fs = FreeSpace.of(cams, np.stack([np.zeros(Y.size), Y.ravel(), Z.ravel()], 1))
    means = torch.tensor([[3.0, 0.1, 0.1], [0.8, 0.1, 0.1], [-1.0, 0.1, 0.1]], requires_grad=True)
    opac = torch.tensor([0.5, 0.5, 0.5], requires_grad=True)
    loss = free_space_loss(opac, means, fs)
    loss.backward()
    assert float(loss.detach()) == pytest.approx(0.5 / 3)
    assert opac.grad.tolist() == pytest.approx([1 / 3, 0.0, 0.0]) and means.grad is None
