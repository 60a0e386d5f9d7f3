"""Random anchors avoid the space that the keyframe points show to be empty."""

import numpy as np
import torch

from atgs.cameras import Camera
from atgs.geometry.free_space import FreeSpace, carve, nearest_depth_grid
from atgs.model.random_anchors import random_anchor_points


def _camera() -> Camera:
    """64x48 camera at the origin looking down +z (OpenCV axes: identity world-to-camera)."""
    return Camera("c", 64, 48, np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]]), np.eye(4))


def _wall(depth: float, x_max: float = 10.0) -> np.ndarray:
    """Points on the plane z = depth, for x < x_max (the rest of the view has no points)."""
    x, y = np.meshgrid(np.linspace(-8, x_max, 90), np.linspace(-6, 6, 60))
    keep = x < x_max
    return np.stack([x[keep], y[keep], np.full(keep.sum(), depth)], 1)


def test_nearest_depth_grid_keeps_the_nearest_point_per_cell():
    cam = _camera()
    pts = np.array([[0.0, 0.0, 10.0], [0.0, 0.0, 4.0], [0.01, 0.0, 7.0]])  # one cell, three depths
    grid, cell = nearest_depth_grid(cam, pts, cells=8)
    assert cell == 8 and grid.shape == (6, 8)
    r, c = 24 // 8, 32 // 8
    assert grid[r, c] == 4.0 and np.isinf(np.delete(grid.ravel(), r * 8 + c)).all()


def test_carve_rejects_samples_in_front_of_the_points_and_keeps_the_rest():
    cam = _camera()
    wall = _wall(10.0, x_max=0.0)  # points on the left half of the view only
    samples = np.array([
        [-1.0, 0.0, 5.0],   # in front of the wall (5 < 0.8 * 10): empty space
        [-1.0, 0.0, 9.0],   # within the margin of the wall: kept
        [-1.0, 0.0, 15.0],  # behind the wall: kept (unseen space)
        [2.0, 0.0, 5.0],    # right half, where no point was measured: kept
        [0.0, 0.0, -3.0],   # behind the camera: seen by no camera, rejected
        [40.0, 0.0, 5.0],   # outside the image: rejected
    ])
    assert carve(samples, wall, [cam]).tolist() == [False, True, True, True, False, False]
    # a second camera whose points do not cover the first sample cannot bring it back
    other = Camera("d", 64, 48, cam.K, np.eye(4) @ np.diag([1.0, 1, 1, 1]))
    assert not carve(samples[:1], wall, [cam, other])[0]


def test_random_anchor_points_fill_only_the_carved_box():
    cam = _camera()
    wall = _wall(10.0)
    box = torch.tensor([[-3.0, -2.0, 2.0], [3.0, 2.0, 14.0]])
    gen = torch.Generator().manual_seed(0)
    pts = random_anchor_points(500, box, FreeSpace.of([cam], wall), gen)
    assert len(pts) == 500
    assert ((pts >= box[0]) & (pts <= box[1])).all()
    # the wall is seen everywhere in this box: nothing is left in front of 0.8 x its depth
    assert float(pts[:, 2].min()) >= 8.0
    assert carve(pts.double().numpy(), wall, [cam]).all()
    # without cameras: the plain uniform samples of the whole box
    plain = random_anchor_points(500, box, None, torch.Generator().manual_seed(0))
    assert len(plain) == 500 and float(plain[:, 2].min()) < 4.0


def test_random_anchor_points_return_fewer_when_the_box_is_empty_space():
    cam = _camera()
    wall = _wall(10.0)
    box = torch.tensor([[-1.0, -1.0, 2.0], [1.0, 1.0, 6.0]])  # all in front of the wall
    pts = random_anchor_points(100, box, FreeSpace.of([cam], wall), torch.Generator().manual_seed(0))
    assert len(pts) == 0
