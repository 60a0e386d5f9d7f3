"""The per-ray free-space term (atgs.geometry.ray_free_space, atgs.train.losses.ray_free_space_loss):
measured depths per camera cell from the points a camera itself sees, and the opacity its rays
accumulate in front of them, against an independent render of the Gaussians chosen by hand."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from atgs.cameras import Camera
from atgs.gaussians import Gaussians
from atgs.geometry.ray_free_space import MeasuredDepths, measured_depth_grid, median_depth_grid, visible_points
from atgs.render import rasterize
from atgs.train.losses import ray_free_space_loss

W, H, FOCAL, WALL = 64, 48, 50.0, 5.0
GREY = 0.7


def front_camera() -> Camera:
    """At the origin, looking down +z (OpenCV axes: the world is the camera frame)."""
    K = np.array([[FOCAL, 0, W / 2], [0, FOCAL, H / 2], [0, 0, 1.0]])
    return Camera("cam", W, H, K, np.eye(4))


def wall_points(step: float = 0.05) -> np.ndarray:
    """A grid of points on the plane z = WALL filling the camera's view."""
    xs = np.arange(-3.5, 3.5, step)
    ys = np.arange(-2.6, 2.6, step)
    X, Y = np.meshgrid(xs, ys)
    return np.stack([X.ravel(), Y.ravel(), np.full(X.size, WALL)], 1)


def grey_image() -> np.ndarray:
    return np.full((H, W, 3), round(GREY * 255), np.uint8)


def gaussians(centres, opacity: float = 0.5, scale: float = 0.15) -> Gaussians:
    c = torch.tensor(centres, dtype=torch.float32).reshape(-1, 3)
    n = c.shape[0]
    return Gaussians(c, torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.full((n, 3), scale),
                     torch.full((n,), opacity, requires_grad=True), torch.full((n, 3), 0.5))


def test_only_the_points_a_camera_sees_measure_its_rays():
    """A wall point behind a red occluder projects onto red pixels: it is not seen, so it does
    not claim the ray through the occluder empty; the grey wall's points do."""
    cam, pts = front_camera(), wall_points()
    img = grey_image()
    img[10:30, 20:40] = (200, 20, 20)  # the occluder's pixels
    seen = visible_points(cam, pts, np.full_like(pts, GREY), img)
    uv, _ = cam.project(pts)
    behind = (uv[:, 0] >= 21) & (uv[:, 0] < 39) & (uv[:, 1] >= 11) & (uv[:, 1] < 29)
    assert behind.any() and not seen[behind].any()
    far = (uv[:, 0] < 18) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    assert seen[far].all()
    grid = measured_depth_grid(cam, pts, np.full_like(pts, GREY), img, cell_px=4)
    assert np.isinf(grid[4:6, 7:8]).all(), "cells inside the occluder are unmeasured"
    assert np.allclose(grid[0, 0], WALL, rtol=1e-3)


def test_a_depth_edge_keeps_its_nearer_side():
    """Cells next to a measured nearer surface take its depth (3x3 minimum), so a Gaussian of the
    nearer surface straddling the edge is never charged."""
    cam = front_camera()
    wall = wall_points()
    left = wall[wall[:, 0] < 0]
    near = wall[wall[:, 0] >= 0] * np.array([1, 1, 0.5])  # the right half at depth 2.5, the same pixels
    pts = np.concatenate([left, near])
    grid = measured_depth_grid(cam, pts, np.full_like(pts, GREY), grey_image(), cell_px=4)
    raw = median_depth_grid(cam, pts, grid.shape[1])
    row, raw_row = grid[6], raw[6]
    edge = int(np.argmax(raw_row < 3))  # first cell of the near surface, from the left
    assert raw_row[edge - 1] == pytest.approx(WALL, rel=1e-3) and raw_row[edge - 2] == pytest.approx(WALL, rel=1e-3)
    assert row[edge - 1] == pytest.approx(2.5, rel=1e-3), "the wall's cell beside the edge takes the nearer depth"
    assert row[edge - 2] == pytest.approx(WALL, rel=1e-3), "one cell only"


def test_a_few_wrong_points_in_front_of_a_uniform_wall_do_not_set_its_depth():
    """Stereo on a grey wall leaves a few grey points in the air; a cell's depth is the median of
    its points, so they neither shield what stands around them nor claim the wall nearer. The
    reference: the depths of each cell's points, sorted by hand."""
    cam = front_camera()
    wall = wall_points(step=0.02)
    rng = np.random.default_rng(0)
    floaters = wall[rng.choice(len(wall), len(wall) // 10, replace=False)] * np.array([1, 1, 0.5])
    pts = np.concatenate([wall, floaters])
    grid = median_depth_grid(cam, pts, 16)
    uv, z = cam.project(pts)
    cell = W / 16
    r, c = 5, 7
    mine = np.sort(z[(uv[:, 1] // cell == r) & (uv[:, 0] // cell == c)])
    assert len(mine) > 10 and mine[0] == pytest.approx(2.5) and grid[r, c] == mine[(len(mine) - 1) // 2]
    assert np.allclose(grid, WALL, rtol=1e-3), "every cell: the wall's depth, not the floaters'"


def measured(frames=(0,)) -> MeasuredDepths:
    pts = wall_points()
    cols = np.full_like(pts, GREY)
    return MeasuredDepths.measure([front_camera()], [(f, pts, cols) for f in frames], lambda s, f: grey_image())


def test_fog_in_front_of_the_wall_is_charged_its_alpha_and_pushed_transparent():
    """Against an independent render: the loss is the mean over the image of the alpha of the
    Gaussians in front of the wall, rendered alone by the slow torch reference; a Gaussian
    behind the wall adds nothing; the gradient lowers the fog's opacity."""
    cam, md = front_camera(), measured()
    fog = [[0.0, 0.0, 2.0], [0.6, -0.3, 3.0]]
    behind = [[0.2, 0.1, 6.0]]
    g = gaussians(fog + behind)
    loss = ray_free_space_loss(g, torch.zeros(3, dtype=torch.bool), md, 0, 0, cam)
    ref = gaussians(fog)
    out = rasterize(ref.means, ref.quats, ref.scales, ref.opacities.detach(), ref.colors, cam.w2c, cam.K, W, H,
                    backend="torch")
    assert float(loss.detach()) == pytest.approx(float(out.alpha.mean()), rel=1e-3)
    loss.backward()
    assert (g.opacities.grad[:2] > 0).all(), "descending the loss makes the fog more transparent"
    assert float(g.opacities.grad[2]) == 0.0


def test_nothing_is_charged_behind_the_wall_or_where_nothing_was_measured():
    cam, md = front_camera(), measured()
    assert ray_free_space_loss(gaussians([[0.0, 0.0, 4.5]]), torch.zeros(1, dtype=torch.bool), md, 0, 0, cam) is None
    blank = MeasuredDepths.measure([cam], [(0, np.zeros((0, 3)), np.zeros((0, 3)))], lambda s, f: grey_image())
    assert not blank.any_measured
    assert ray_free_space_loss(gaussians([[0.0, 0.0, 2.0]]), torch.zeros(1, dtype=torch.bool), blank, 0, 0, cam) is None


def test_moving_gaussians_are_judged_only_at_the_frames_that_were_measured():
    """A per-keyframe anchor's Gaussian may stand, between keyframes, where a ray was empty at
    both: it is charged at a measured frame only; a static one at every frame."""
    cam, md = front_camera(), measured(frames=(4,))
    fog = [[0.0, 0.0, 2.0]]
    moving, static = torch.ones(1, dtype=torch.bool), torch.zeros(1, dtype=torch.bool)
    assert ray_free_space_loss(gaussians(fog), moving, md, 0, 5, cam) is None
    assert float(ray_free_space_loss(gaussians(fog), moving, md, 0, 4, cam)) > 0
    assert float(ray_free_space_loss(gaussians(fog), static, md, 0, 5, cam)) > 0


def test_a_gaussian_straddling_a_depth_edge_is_charged_only_on_the_rays_it_occludes():
    """A Gaussian at depth 3 in front of the wall's left half (depth 5) but behind the right
    half's nearer surface (depth 2): only the pixels over the wall count."""
    cam = front_camera()
    wall = wall_points()
    left = wall[wall[:, 0] < 0]
    right = wall[wall[:, 0] >= 0] * np.array([1, 1, 0.4])  # depth 2, the same pixels as x >= 0 on the wall
    pts = np.concatenate([left, right])
    md = MeasuredDepths.measure([cam], [(0, pts, np.full_like(pts, GREY))], lambda s, f: grey_image())
    g = gaussians([[-0.4, 0.0, 3.0]], opacity=0.9, scale=0.3)
    loss = ray_free_space_loss(g, torch.zeros(1, dtype=torch.bool), md, 0, 0, cam)
    out = rasterize(g.means, g.quats, g.scales, g.opacities.detach(), g.colors, cam.w2c, cam.K, W, H, backend="torch")
    depth = md.pixel_depths(0, 0)
    ref = (out.alpha * (torch.isfinite(depth) & (depth > 3.0 / md.margin))).sum() / (W * H)
    assert float(ref) > 0 and float(ref) < 0.8 * float(out.alpha.mean())
    assert float(loss) == pytest.approx(float(ref), rel=1e-3)


def test_at_a_measured_frame_every_gaussian_is_judged_by_that_frame():
    """A walker stood at depth 2 at frame 3 and left: the static depth (the nearest over the
    measured frames) is 2, so at an unmeasured frame a static Gaussian at depth 3 is not charged;
    at frame 0, which measured the wall at 5 behind it, it is (a ghost of the walker), and at
    frame 3, where the walker was in front of it, it is not."""
    cam = front_camera()
    wall = wall_points()
    walker = wall * np.array([1, 1, 0.4])
    grey = np.full_like(wall, GREY)
    md = MeasuredDepths.measure([cam], [(0, wall, grey), (3, walker, grey)], lambda s, f: grey_image())
    ghost, static = [[0.0, 0.0, 3.0]], torch.zeros(1, dtype=torch.bool)
    assert ray_free_space_loss(gaussians(ghost), static, md, 0, 1, cam) is None
    assert ray_free_space_loss(gaussians(ghost), static, md, 0, 3, cam) is None
    assert float(ray_free_space_loss(gaussians(ghost), static, md, 0, 0, cam).detach()) > 0
