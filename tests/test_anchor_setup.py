"""A new model's anchors read one keyframe at a time (atgs.model.anchor_setup): the same anchors
as the whole-capture reference (split_static + init_anchors over every point at once), however
the keyframes are spread over workers, never holding more than one keyframe's points."""

from __future__ import annotations

import threading
from dataclasses import replace

import numpy as np
import pytest
import torch

from builders import ring_cameras, tiny_config
from atgs.keyframe_cloud import ArrayPointCloud
from atgs.model.anchor_setup import anchors_from_clouds
from atgs.model.anchors import STATIC, init_anchors, split_static
from atgs.model.atgs_model import ATGSModel, num_segments_for
from atgs.timeline import Timeline


def _capture(K: int = 5, seed: int = 0):
    """A static plane seen (with noise) at every keyframe, a cube moving along x and, as the
    motion points, a sphere moving along y: (points, keyframes, motion points, their keyframes)."""
    gen = torch.Generator().manual_seed(seed)
    grid = torch.stack(torch.meshgrid(torch.linspace(0, 2, 24), torch.linspace(0, 2, 24), indexing="ij"), -1)
    plane = torch.cat([grid.reshape(-1, 2), torch.zeros(576, 1)], 1)
    pts, kf, mpts, mkf = [], [], [], []
    for k in range(K):
        pts += [plane + 0.003 * torch.randn(plane.shape, generator=gen),
                torch.rand(80, 3, generator=gen) * 0.25 + torch.tensor([0.35 * k, 1.0, 0.5])]
        kf += [torch.full((576 + 80,), k)]
        d = torch.randn(120, 3, generator=gen)
        mpts.append(0.2 * d / d.norm(dim=1, keepdim=True) + torch.tensor([1.0, 0.3 * k, 1.0]))
        mkf.append(torch.full((120,), k))
    return torch.cat(pts), torch.cat(kf), torch.cat(mpts), torch.cat(mkf)


def _clouds(K: int = 5, shuffle: bool = True):
    pts, kf, mpts, mkf = _capture(K)
    order = torch.randperm(len(pts), generator=torch.Generator().manual_seed(3)) if shuffle else torch.arange(len(pts))
    return (ArrayPointCloud(pts[order].numpy(), kf[order].numpy(), K), ArrayPointCloud(mpts.numpy(), mkf.numpy(), K),
            pts, kf, mpts, mkf)


def _timeline(cfg, K: int, frames: int = 21) -> Timeline:
    return Timeline(frames, K, cfg.window, num_segments_for(cfg, frames))


@pytest.mark.parametrize("layout", ["split", "per-keyframe"])
def test_anchors_equal_the_whole_capture_reference(layout):
    K, voxel = 5, 0.1
    cfg = replace(tiny_config(K=K), anchor_layout=layout, voxel_size=voxel, static_voxel_factor=0.5,
                  max_anchors_per_keyframe=0)
    cloud, motion, pts, kf, mpts, mkf = _clouds(K)
    got = anchors_from_clouds(cfg, _timeline(cfg, K), cloud, list(range(0, 21, 5)), motion, list(range(0, 21, 5)),
                              ring_cameras(3), None, seed=0)
    # the reference: every point at once, the static vote over all of them, then init_anchors
    if layout == "split":
        kf = torch.where(split_static(pts, kf, 2 * voxel, cfg.static_fraction), STATIC, kf)
    ref = init_anchors(torch.cat([pts, mpts]), torch.cat([kf, mkf]), voxel, 0, static_voxel_factor=0.5)
    assert got.voxel_size == ref.voxel_size
    assert torch.equal(got.keyframe, ref.keyframe)
    assert torch.equal(got.mu, ref.mu)
    assert torch.equal(got.log_scale, ref.log_scale)
    if layout == "split":  # the plane is static, the cube and the sphere are not
        assert 0 < int((got.keyframe == STATIC).sum()) < len(got.mu)
        assert float(got.mu[got.keyframe == STATIC][:, 2].abs().max()) < 0.05


class _Board:
    """all_gather_object between threads (a stand-in for atgs.train.distributed.Workers)."""

    def __init__(self, world: int) -> None:
        self.slots = [None] * world
        self.barrier = threading.Barrier(world)


class _ThreadSpread:
    def __init__(self, rank: int, board: _Board) -> None:
        self.rank, self.world, self.board = rank, len(board.slots), board

    def gather_everywhere(self, obj) -> list:
        self.board.slots[self.rank] = obj
        self.board.barrier.wait()
        out = list(self.board.slots)
        self.board.barrier.wait()  # nobody writes the next gather's slot before all have read this one
        return out


class _OneKeyframeAtATime(ArrayPointCloud):
    """Refuses to be read whole; records the most rows read at once."""

    most = 0

    def rows(self, k):
        r = super().rows(k)
        _OneKeyframeAtATime.most = max(_OneKeyframeAtATime.most, len(r))
        return r

    def whole(self):
        raise AssertionError("the set-up read every point at once")


@pytest.mark.parametrize("world", [2, 3])
def test_spread_over_workers_gives_the_same_anchors(world):
    """Voxel size drawn from samples, a cap per keyframe, random anchors carved by the points:
    every random draw comes from its group's generator, so the spread set-up equals one process's."""
    K = 5
    cfg = replace(tiny_config(K=K), anchor_layout="split", voxel_size=0.0, max_anchors_per_keyframe=40,
                  random_anchors=50, carve_random_anchors=True)
    pts, kf, mpts, mkf = _capture(K)
    cloud = _OneKeyframeAtATime(pts.numpy(), kf.numpy(), K)
    motion = _OneKeyframeAtATime(mpts.numpy(), mkf.numpy(), K)
    cams, tl, kfs = ring_cameras(4, radius=4.0), _timeline(cfg, K), list(range(0, 21, 5))

    def build(spread=None):
        return anchors_from_clouds(cfg, tl, cloud, kfs, motion, kfs, cams, None, seed=7, spread=spread)

    alone = build()
    assert _OneKeyframeAtATime.most == 576 + 80  # one keyframe's points at a time
    board, results = _Board(world), [None] * world

    def worker(r):
        results[r] = build(_ThreadSpread(r, board))

    threads = [threading.Thread(target=worker, args=(r,)) for r in range(world)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    for got in results:
        assert got is not None
        assert got.voxel_size == alone.voxel_size
        for name in ("mu", "log_scale", "keyframe"):
            assert torch.equal(getattr(got, name), getattr(alone, name)), name
    # the cap drew: 40 of the static group's (plane and random) anchors, at most 40 of each keyframe's
    assert int((alone.keyframe == STATIC).sum()) == 40
    assert max(int((alone.keyframe == k).sum()) for k in range(K)) == 40


def test_a_model_from_clouds_equals_one_from_points_in_any_order():
    """The points' order in the file does not matter: the groups are read by keyframe."""
    K = 5
    cfg = replace(tiny_config(K=K), anchor_layout="split", max_anchors_per_keyframe=60)
    cloud, motion, pts, kf, mpts, mkf = _clouds(K, shuffle=True)
    kfs = list(range(0, 21, 5))
    a = ATGSModel.from_clouds(cfg, cloud, kfs, 21, 10.0, ring_cameras(3), seed=2, motion_cloud=motion,
                              motion_keyframes=kfs)
    b = ATGSModel.from_points(cfg, pts, kf, kfs, 21, 10.0, ring_cameras(3), seed=2, motion_points=mpts,
                              motion_point_keyframes=mkf, motion_keyframes=kfs)
    assert torch.equal(a.anchor_mu, b.anchor_mu) and torch.equal(a.anchor_keyframe, b.anchor_keyframe)
    assert torch.equal(a.bbox_min, b.bbox_min) and torch.equal(a.bbox_max, b.bbox_max)


def test_an_empty_capture_starts_from_the_seen_space():
    cfg = replace(tiny_config(K=3), anchor_layout="split")
    empty = ArrayPointCloud(np.zeros((0, 3)), np.zeros(0), 3)
    a = anchors_from_clouds(cfg, _timeline(cfg, 3), empty, [0, 10, 20], None, [], ring_cameras(3, radius=3.0),
                            None, seed=0)
    assert len(a.mu) > 0 and bool((a.keyframe == STATIC).all())
    per = anchors_from_clouds(replace(cfg, anchor_layout="per-keyframe"), _timeline(cfg, 3), empty, [0, 10, 20],
                              None, [], ring_cameras(3, radius=3.0), None, seed=0)
    assert sorted(set(per.keyframe.tolist())) == [0, 1, 2]
