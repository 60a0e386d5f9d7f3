"""Moving-content points (atgs.data.moving_points): masks, visual hull, and their use by the model.

The hull is checked against an analytic sphere seen by a ring of cameras (exact silhouettes by
ray-sphere intersection); the masks against painted squares; the model against the keyframes
the points were given."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from atgs.data.errors import DataError
from atgs.data.motion_measure import box_downsample
from atgs.data.moving_points import (MotionPointsConfig, background, foreground_mask, hull_votes, motion_keyframes,
                                     motion_mask, motion_points, visual_hull)
from atgs.data.scene import MemoryScene, PreparedScene, write_prepared_scene
from atgs.model.anchors import STATIC
from atgs.model.atgs_model import ATGSModel
from atgs.timeline import evenly_spaced
from builders import ring_cameras, tiny_config


def _sphere_hits(cam, center: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact silhouette (pixels whose centre ray meets the sphere) and the first hit points."""
    j, i = np.mgrid[0:cam.height, 0:cam.width]
    d_cam = np.stack([(i + 0.5 - cam.cx) / cam.fx, (j + 0.5 - cam.cy) / cam.fy, np.ones_like(i, float)], -1)
    d = d_cam @ cam.R  # camera -> world directions (R is world -> camera)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    oc = cam.center - center
    b = d @ oc
    disc = b * b - (oc @ oc - radius * radius)
    t = -b - np.sqrt(np.maximum(disc, 0))
    return (disc >= 0) & (-b + np.sqrt(np.maximum(disc, 0)) > 0), cam.center + t[..., None] * d


def _sphere_mask(cam, center: np.ndarray, radius: float) -> np.ndarray:
    return _sphere_hits(cam, center, radius)[0]


def _ring(n=8, size=(96, 72)):
    cams = ring_cameras(n, size=size, radius=4.0, height=0.0)
    # alternate elevations so that the cones also close the sphere at its poles
    from atgs.cameras import Camera, look_at
    out = []
    for k, c in enumerate(cams):
        eye = c.center + np.array([0.0, 0.0, 2.0 if k % 2 else -2.0])
        out.append(Camera(c.name, c.width, c.height, c.K, look_at(eye, np.zeros(3), np.array([0.0, 0.0, 1.0]))))
    return out


def test_motion_keyframes_contain_the_geometry_keyframes() -> None:
    for F in (2, 7, 60, 120, 301, 1000):
        for K in (1, 2, 5, 6, 9):
            for r in (1, 2, 4, 5):
                m = motion_keyframes(F, K, r)
                assert set(evenly_spaced(F, K)) <= set(m), (F, K, r)
                assert m == sorted(set(m)) and m[0] == 0 and m[-1] == F - 1


def test_mask_finds_the_moving_square_not_the_noise() -> None:
    rng = np.random.default_rng(0)
    frames = [rng.integers(90, 110, (48, 64, 3)).astype(np.uint8) for _ in range(9)]
    bg = background([box_downsample(f, 64) for f in frames])
    frame = frames[4].copy()
    frame[10:30, 20:44] = 250  # an object in front of the background
    m = motion_mask(box_downsample(frame, 64), bg, MotionPointsConfig())
    truth = np.zeros((48, 64), bool)
    truth[10:30, 20:44] = True
    assert m[truth].mean() > 0.99  # the object
    ring = np.zeros((48, 64), bool)
    ring[9:31, 19:45] = True  # the 3x3 blur may widen a strong edge by one pixel
    assert not m[~ring].any()  # sensor noise (+-10 levels) is not motion
    # a frame like the others moves nowhere
    assert not motion_mask(box_downsample(frames[2], 64), bg, MotionPointsConfig()).any()


def test_hull_of_a_sphere_hugs_the_sphere() -> None:
    cams = _ring()
    c, r = np.array([0.3, -0.2, 0.1]), 0.6
    masks = [_sphere_mask(cam, c, r) for cam in cams]
    box = np.array([[-2.0, -2.0, -2.0], [2.0, 2.0, 2.0]])
    cfg = MotionPointsConfig(resolution=32, subdivide=4)
    hull, on_surface, fine = visual_hull(cams, masks, box, cfg)
    pts = hull[on_surface]
    assert len(pts) > 200
    dist = np.linalg.norm(pts - c, axis=1) - r
    # a hull contains the object: no surface voxel inside the sphere by more than a voxel diagonal
    assert dist.min() > -fine * np.sqrt(3)
    # and hugs it: 8 views from two elevations leave corners of a few voxels
    assert np.median(np.abs(dist)) < 0.08 * r, np.median(np.abs(dist))
    assert dist.max() < 0.5 * r
    # every voxel well inside the sphere is in the hull; points far from it are not
    rng = np.random.default_rng(1)
    inside = c + rng.normal(size=(500, 3)) * 0.1
    inside = inside[np.linalg.norm(inside - c, axis=1) < 0.8 * r]
    assert hull_votes(inside, 0.01, cams, masks, 3, 1).all()
    far = np.array([[1.6, 0.0, 0.0], [-1.5, 1.2, 0.3], [0.0, 0.0, 1.7]])
    assert not hull_votes(far, 0.01, cams, masks, 3, 1).any()


def test_space_few_cameras_see_is_rejected() -> None:
    cams = _ring()
    masks = [np.ones((c.height, c.width), bool) for c in cams]  # everything "moves"
    x = np.array([[0.0, 0.0, 0.0], [3.6, 0.0, 0.0]])  # the centre; next to cam00, behind most cameras
    n_see = [sum(bool((cam.project(p[None])[1] > 0)[0]) and 0 <= cam.project(p[None])[0][0, 0] < cam.width
                 and 0 <= cam.project(p[None])[0][0, 1] < cam.height for cam in cams) for p in x]
    assert n_see[0] == len(cams) and n_see[1] < len(cams) // 2
    votes = hull_votes(x, 0.01, cams, masks, 2, 1, min_see=len(cams) // 2)
    assert votes.tolist() == [True, False]
    assert hull_votes(x, 0.01, cams, masks, 1, 1, min_see=0)[1]  # without the rule the phantom stays


def _moving_sphere_frames(cams, F, radius=0.4):
    """Frames of a textured static background and a bright sphere moving along x."""
    rng = np.random.default_rng(3)
    bgs = [rng.integers(0, 120, (c.height, c.width, 3)).astype(np.uint8) for c in cams]
    centers = [np.array([-1.0 + 2.0 * f / (F - 1), 0.0, 0.0]) for f in range(F)]

    def frame_of(ci, f):
        img = bgs[ci].copy()
        mask, hit = _sphere_hits(cams[ci], centers[f], radius)
        n = (hit[mask] - centers[f]) / radius  # a smooth texture fixed to the sphere's surface
        img[mask] = np.clip(np.stack([170 + 80 * n[:, 0], 150 + 90 * n[:, 1], 60 + 50 * n[:, 2]], -1), 0, 255)
        return img
    return frame_of, centers


def test_moving_sphere_gives_points_where_it_is_at_each_keyframe() -> None:
    cams, F = _ring(), 13
    frame_of, centers = _moving_sphere_frames(cams, F)
    kfs = motion_keyframes(F, 3, 3)
    box = np.array([[-2.0, -2.0, -2.0], [2.0, 2.0, 2.0]])
    mp = motion_points(frame_of, cams, F, kfs, box, MotionPointsConfig(resolution=32, long_side=96), progress=False)
    assert mp.keyframes == kfs and mp.stats["keyframes"] == len(kfs)
    for j, f in enumerate(kfs):
        pts = mp.points[mp.point_keyframes == j]
        assert len(pts) > 50
        d = np.linalg.norm(pts - centers[f], axis=1) - 0.4
        assert np.median(np.abs(d)) < 0.1, (f, np.median(np.abs(d)))
    # coloured from the pixels that hold them (the sphere's colours, not the dark background)
    assert (mp.colors[:, 0] > 80 / 255).mean() > 0.95


def test_static_scene_gives_no_motion_keyframes() -> None:
    cams, F = _ring(), 9
    rng = np.random.default_rng(4)
    bgs = [rng.integers(0, 255, (c.height, c.width, 3)).astype(np.uint8) for c in cams]
    mp = motion_points(lambda ci, f: bgs[ci], cams, F, motion_keyframes(F, 2, 4),
                       np.array([[-2.0] * 3, [2.0] * 3]), MotionPointsConfig(resolution=16), progress=False)
    assert mp.keyframes == [] and len(mp.points) == 0 and mp.stats["keyframes"] == 0


def test_model_puts_motion_points_at_their_keyframes() -> None:
    cams, F = ring_cameras(4), 13
    geo_kfs = evenly_spaced(F, 3)
    rng = np.random.default_rng(5)
    wall = rng.uniform(-1, 1, (400, 3))  # static: at every geometry keyframe
    mover = np.array([-3.0, 0.0, 0.0]) + rng.normal(size=(40, 3)) * 0.05  # stereo saw it at geometry keyframe 1 only
    pts = np.concatenate([wall] * 3 + [mover])
    pkf = np.concatenate([np.repeat(np.arange(3), 400), np.ones(40, np.int64)])
    mkfs = motion_keyframes(F, 3, 3)  # 7 keyframes
    mpts = np.concatenate([np.array([2.0 + j, 0.0, 0.0]) + rng.normal(size=(30, 3)) * 0.05 for j in range(len(mkfs))])
    mk = np.repeat(np.arange(len(mkfs)), 30)
    cfg = tiny_config(K=0, W=3, random_anchors=0)
    model = ATGSModel.from_points(cfg, torch.tensor(pts, dtype=torch.float32), torch.tensor(pkf), geo_kfs, F, 10.0,
                                  cams, motion_points=torch.tensor(mpts, dtype=torch.float32),
                                  motion_point_keyframes=torch.tensor(mk), motion_keyframes=mkfs)
    assert model.num_keyframes == len(mkfs)
    kf = model.anchor_keyframe
    mu = model.anchor_mu
    moving = mu[:, 0] > 1.5
    assert (kf[~moving & (mu[:, 0] > -2.5)] == STATIC).all()  # the wall stays one static set
    # moving geometry points (at geometry keyframe 1, frame 6) go to the model keyframe of frame 6
    assert model.timeline.keyframe_frames()[3] == geo_kfs[1] == 6
    geo_moving = mu[:, 0] < -2.5
    assert geo_moving.any() and (kf[geo_moving] == 3).all()
    for j in range(len(mkfs)):  # each cluster of motion points sits at its own keyframe
        sel = moving & ((mu[:, 0] - (2.0 + j)).abs() < 0.4)
        assert sel.any() and (kf[sel] == j).all()
    # without motion points: the geometry keyframes only
    plain = ATGSModel.from_points(cfg, torch.tensor(pts, dtype=torch.float32), torch.tensor(pkf), geo_kfs, F, 10.0, cams)
    assert plain.num_keyframes == 3


def test_scene_round_trip_and_missing_file(tmp_path) -> None:
    cams, F = ring_cameras(3), 5
    from atgs.data.moving_points import MotionPoints
    mp = MotionPoints([0, 2, 4], np.array([[0.0, 0, 0], [1, 1, 1], [2, 2, 2]]), np.full((3, 3), 0.5, np.float32),
                      np.array([0, 1, 2]), {"keyframes": 3})
    scene = MemoryScene(cams, F, keyframes=[0, 4], points=np.zeros((200, 3)) + np.arange(200)[:, None] * 0.01,
                        point_keyframes=np.repeat([0, 1], 100), **mp.scene_fields())
    out = write_prepared_scene(tmp_path / "s", scene, lambda ci, f: np.zeros((24, 32, 3), np.uint8))
    s = PreparedScene.load(out)
    assert s.motion_keyframes == [0, 2, 4]
    np.testing.assert_allclose(s.motion_points, mp.points, atol=1e-6)
    assert s.motion_point_keyframes.tolist() == [0, 1, 2]
    (out / "motion_points.ply").unlink()
    with pytest.raises(DataError, match="motion_points.ply: not found"):
        PreparedScene.load(out)


def test_photo_selection_finds_depth_where_the_hull_is_deep() -> None:
    """A front-facing rig's hull is deep along the view direction; the photo-consistent choice
    puts the points on the surface, the hull's surface voxels do not."""
    from atgs.cameras import Camera, look_at
    W, H, f = 96, 72, 90.0
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])
    cams = [Camera(f"c{k}", W, H, K, look_at(np.array([x, -4.0, z]), np.array([x * 0.2, 0.0, z * 0.2]),
                                            np.array([0.0, 0.0, 1.0])))
            for k, (x, z) in enumerate([(-0.6, -0.3), (0.0, -0.3), (0.6, -0.3), (-0.6, 0.3), (0.0, 0.3), (0.6, 0.3)])]
    F = 5
    frame_of, centers = _moving_sphere_frames(cams, F)
    box = np.array([[-2.0, -2.0, -2.0], [2.0, 2.0, 2.0]])
    res = {}
    for select in ("photo", "surface"):
        mp = motion_points(frame_of, cams, F, [2], box, MotionPointsConfig(resolution=32, long_side=96, select=select),
                           progress=False)
        res[select] = np.median(np.abs(np.linalg.norm(mp.points - centers[2], axis=1) - 0.4))
    assert res["photo"] < 0.1 < res["surface"], res


def test_foreground_masks_replace_the_frame_difference() -> None:
    """A capture with foreground masks (a standing performer: the frames do not change) gets its
    motion points from the masks; without them, nothing moves and there are none."""
    cams, F = _ring(), 9
    rng = np.random.default_rng(5)
    frames = [rng.integers(0, 255, (c.height, c.width, 3)).astype(np.uint8) for c in cams]
    center = np.array([0.2, -0.1, 0.0])
    masks = [_sphere_mask(c, center, 0.4) for c in cams]
    kfs = motion_keyframes(F, 2, 2)
    box = np.array([[-2.0] * 3, [2.0] * 3])
    cfg = MotionPointsConfig(resolution=32, long_side=96, select="surface")
    none = motion_points(lambda ci, f: frames[ci], cams, F, kfs, box, cfg, progress=False)
    assert len(none.points) == 0
    mp = motion_points(lambda ci, f: frames[ci], cams, F, kfs, box, cfg, progress=False, mask_of=lambda ci, f: masks[ci])
    assert mp.keyframes == kfs and len(mp.points) > 50 * len(kfs)
    d = np.linalg.norm(mp.points - center, axis=1) - 0.4
    assert np.median(np.abs(d)) < 0.1
    # the mask at the working resolution is the box average of the full one, foreground from one half
    small = foreground_mask(masks[0], 48)
    ref = masks[0].reshape(36, 2, 48, 2).mean(axis=(1, 3)) >= 0.5  # 2x2 blocks
    assert small.shape == (36, 48) and np.array_equal(small, ref) and small.any()
