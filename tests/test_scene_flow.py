"""Optical flow (atgs.data.flow) and the anchors' initial velocities from it (atgs.train.scene_flow),
against analytic motion: a shifted texture, and points of a textured plane moving with a known
3D velocity seen by a ring of pinhole cameras."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from atgs.cameras import Camera, look_at
from atgs.data.flow import pyramid, sample, track_points
from atgs.train.scene_flow import SceneFlowConfig, initial_velocities, robust_velocity


def _texture(seed: int = 0, size: int = 96) -> torch.Tensor:
    """Random texture with detail at every scale, like a photograph: uniform noise on grids of 4
    to 32-pixel cells (bicubic), summed."""
    g = torch.Generator().manual_seed(seed)
    t = sum(F.interpolate(torch.rand(1, 1, size // c, size // c, generator=g), size=(size, size), mode="bicubic",
                          align_corners=False) for c in (4, 8, 16, 32))
    return (t / 4).clamp(0, 1)


def _shifted(tex: torch.Tensor, h: int, w: int, dx: float, dy: float) -> torch.Tensor:
    ys, xs = torch.meshgrid(torch.arange(h) + 0.5 + 8, torch.arange(w) + 0.5 + 8, indexing="ij")
    return sample(tex, torch.stack([xs - dx, ys - dy], -1)[None])[0, 0]


@pytest.mark.parametrize("shift", [(0.4, -0.3), (7.3, -4.6), (-13.0, 9.5)])
def test_track_points_recovers_a_shift(shift):
    torch.manual_seed(0)
    tex = _texture(size=160)
    a, b = _shifted(tex, 96, 128, 0, 0), _shifted(tex, 96, 128, *shift)
    pts = torch.rand(200, 2) * torch.tensor([88.0, 56.0]) + 20
    to, res = track_points(pyramid(a, 4), pyramid(b, 4), pts)
    err = (to - pts - torch.tensor(shift)).norm(dim=1)
    assert float(err.median()) < 0.1
    assert float((err < 0.5).float().mean()) > 0.9
    assert float(res.median()) < 0.03


def test_a_batch_of_image_pairs_tracks_like_each_pair_alone():
    tex = _texture(size=160)
    shifts = [(2.5, 1.0), (-5.0, 3.5)]
    firsts = [_shifted(tex, 96, 128, 0, 0), _shifted(tex, 96, 128, 1.0, -2.0)]
    seconds = [_shifted(tex, 96, 128, *s) for s in shifts]
    seconds[1] = _shifted(tex, 96, 128, 1.0 - 5.0, -2.0 + 3.5)
    g = torch.Generator().manual_seed(2)
    pts = torch.rand(2, 50, 2, generator=g) * torch.tensor([88.0, 56.0]) + 20
    to, res = track_points(pyramid(torch.stack(firsts), 4), pyramid(torch.stack(seconds), 4), pts)
    for i in range(2):
        one, one_res = track_points(pyramid(firsts[i], 4), pyramid(seconds[i], 4), pts[i])
        assert torch.allclose(to[i], one, atol=1e-3) and torch.allclose(res[i], one_res, atol=1e-4)
        assert float((to[i] - pts[i] - torch.tensor(shifts[i])).norm(dim=1).median()) < 0.1


def test_track_points_flags_a_window_that_does_not_match():
    tex, other = _texture(0, 160), _texture(1, 160)
    a, b = _shifted(tex, 96, 128, 0, 0), _shifted(other, 96, 128, 0, 0)
    pts = torch.tensor([[40.0, 40.0], [80.0, 50.0]])
    _, res = track_points(pyramid(a, 4), pyramid(b, 4), pts)
    _, res_same = track_points(pyramid(a, 4), pyramid(a, 4), pts)
    assert float(res.min()) > 5 * float(res_same.max()) + 0.02


def _camera(eye, up=(0.0, 0.0, 1.0), f: float = 120.0, w: int = 160, h: int = 120) -> Camera:
    """A pinhole camera at ``eye`` looking at the origin."""
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
    return Camera("c", w, h, K, look_at(np.asarray(eye, dtype=np.float64), np.zeros(3), np.asarray(up)))


def _ring(n: int, radius: float = 4.0) -> list[Camera]:
    return [_camera([radius * np.cos(2 * np.pi * i / n), radius * np.sin(2 * np.pi * i / n), 0.0]) for i in range(n)]


def test_robust_velocity_ignores_cameras_that_see_something_else():
    cams = _ring(6)
    x = torch.tensor([[0.1, -0.2, 0.05], [-0.3, 0.2, -0.1]])
    v_true = torch.tensor([[0.02, -0.01, 0.015], [-0.01, 0.03, 0.0]])
    from atgs.train.scene_flow import _project

    jac, flow = [], []
    for cam in cams:
        uv0, _, J = _project(cam, x - 0.5 * v_true)
        uv1, _, _ = _project(cam, x + 0.5 * v_true)
        jac.append(_project(cam, x)[2])
        flow.append(uv1 - uv0)
    jac, flow = torch.stack(jac, 1), torch.stack(flow, 1)
    flow[0, 1] = torch.tensor([0.0, 0.0])  # an occluder in two cameras: zero flow
    flow[0, 4] = torch.tensor([3.0, -2.0])
    valid = torch.ones(2, 6, dtype=torch.bool)
    valid[1, 2] = False
    v, ok = robust_velocity(jac, flow, valid, inlier_px=0.2, min_cameras=3)
    assert ok.all()
    assert torch.allclose(v, v_true, atol=2e-3)
    # too few agreeing cameras: not measured, velocity 0
    v, ok = robust_velocity(jac[:, :2], flow[:, :2], valid[:, :2], inlier_px=0.2, min_cameras=3)
    assert not ok.any() and (v == 0).all()


def _render_plane(cam: Camera, tex: torch.Tensor, offset: np.ndarray) -> torch.Tensor:
    """Grey image of a textured square in the z = 0 plane (|x|, |y| < 1.5, translated by ``offset``)
    over a flat grey background, seen by ``cam``."""
    h, w = cam.height, cam.width
    ys, xs = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    rays = np.stack([(xs - cam.cx) / cam.fx, (ys - cam.cy) / cam.fy, np.ones_like(xs)], -1) @ cam.R
    origin = -cam.R.T @ cam.t
    s = (offset[2] - origin[2]) / rays[..., 2]
    p = origin + s[..., None] * rays - offset
    inside = (s > 0) & (np.abs(p[..., 0]) < 1.5) & (np.abs(p[..., 1]) < 1.5)
    uv = torch.from_numpy(np.stack([(p[..., 0] + 1.5) / 3.0, (p[..., 1] + 1.5) / 3.0], -1)).float() * tex.shape[-1]
    img = sample(tex, uv[None])[0, 0]
    return torch.where(torch.from_numpy(inside), img, torch.full_like(img, 0.5))


@pytest.mark.parametrize("long_side", [480, 120])  # 160x120 images as they are, and downscaled to 120x90
def test_initial_velocities_of_a_moving_textured_plane(long_side):
    # cameras above the plane looking down at it, so every camera sees its texture
    cams = [_camera([1.5 * np.cos(2 * np.pi * i / 5), 1.5 * np.sin(2 * np.pi * i / 5), 4.0], up=(0.0, 1.0, 0.0), f=110.0)
            for i in range(5)]
    tex = _texture(3, 128)
    speed = np.array([0.03, -0.02, 0.0])  # world units per frame
    frames = 7

    def grey(ci: int, f: int) -> torch.Tensor:
        return _render_plane(cams[ci], tex, speed * f)

    # anchors of keyframes at frames 0, 3, 6 on the plane where it is then, plus static ones
    g = torch.Generator().manual_seed(0)
    mus, kfs = [], []
    for k, f in enumerate((0, 3, 6)):
        p = (torch.rand(60, 2, generator=g) - 0.5) * 2.0
        mus.append(torch.cat([p, torch.zeros(60, 1)], 1) + torch.tensor(speed * f, dtype=torch.float32))
        kfs.append(torch.full((60,), k))
    mus.append(torch.zeros(5, 3))
    kfs.append(torch.full((5,), -1))
    mu, kf = torch.cat(mus), torch.cat(kfs)
    vel, stats = initial_velocities(mu, kf, 0.1, [0, 3, 6], frames, cams, grey,
                                    SceneFlowConfig(max_tracked=30, min_cameras=3, long_side=long_side))
    per_interval = (frames - 1) / 2  # frames per keyframe interval
    want = torch.tensor(speed * per_interval, dtype=torch.float32)
    moving = kf >= 0
    assert stats["measured"] >= 0.8 * stats["tracked"]
    err = (vel[moving] - want).norm(dim=1)
    assert float(err.median()) < 0.1 * float(want.norm())
    assert (vel[~moving] == 0).all()
    # measured a share of the keyframes at a time (workers, atgs.train.scene_setup): the same
    # velocities for those keyframes, 0 for the others (max_tracked 30 of 60: a random subset)
    flow_cfg = SceneFlowConfig(max_tracked=30, min_cameras=3, long_side=long_side)
    part, _ = initial_velocities(mu, kf, 0.1, [0, 3, 6], frames, cams, grey, flow_cfg, keyframes=[2, 0])
    assert torch.equal(part[(kf == 0) | (kf == 2)], vel[(kf == 0) | (kf == 2)])
    assert (part[kf == 1] == 0).all() and (vel[kf == 1] != 0).any()


def test_the_prior_keeps_a_direction_the_cameras_hardly_see_near_zero():
    # three close cameras side by side looking along +z: motion in depth barely moves the image
    cams = []
    for dx in (-0.05, 0.0, 0.05):
        w2c = np.eye(4)
        w2c[:3, 3] = [-dx, 0.0, 5.0]
        cams.append(Camera("c", 160, 120, np.array([[120.0, 0, 80], [0, 120.0, 60], [0, 0, 1]]), w2c))
    from atgs.train.scene_flow import _project

    x = torch.tensor([[0.3, -0.2, 0.0]])
    v_true = torch.tensor([[0.05, 0.02, 0.0]])  # lateral: what every camera sees
    g = torch.Generator().manual_seed(1)
    jac = torch.stack([_project(c, x)[2] for c in cams], 1)
    flow = torch.einsum("ncij,nj->nci", jac, v_true) + 0.3 * torch.randn(1, 3, 2, generator=g)  # tracking noise
    valid = torch.ones(1, 3, dtype=torch.bool)
    free, _ = robust_velocity(jac, flow, valid, inlier_px=2.0, min_cameras=3)
    ridge = (0.5 / 0.1) ** 2  # the trainer's prior: 0.5 px of noise, one 0.1 voxel per frame
    held, ok = robust_velocity(jac, flow, valid, inlier_px=2.0, min_cameras=3, ridge=ridge)
    assert ok.all()
    assert abs(float(free[0, 2])) > 0.5, "without the prior the noise is amplified along the depth"
    assert abs(float(held[0, 2])) < 0.1
    assert torch.allclose(held[0, :2], v_true[0, :2], atol=0.02)
