"""Static content modelled once (split anchor layout) and the final pruning of anchors that
never contributed."""


import numpy as np
import pytest
import torch

from builders import side_camera
from atgs.model.anchors import STATIC, split_static
from atgs.model.atgs_model import ATGSModel
from atgs.train.config import DensifyConfig, preset
from atgs.timeline import evenly_spaced
from atgs.train.densify import DensifyStats, prune_final


def _split_static_bruteforce(points, keyframes, cell, min_fraction):
    K = len(set(keyframes.tolist()))
    need = max(2, int(np.ceil(min_fraction * K)))
    cells = [tuple(np.round(p / cell).astype(int)) for p in points.double().numpy()]
    out = []
    for c in cells:
        seen = {int(k) for c2, k in zip(cells, keyframes.tolist()) if c2 == c}
        out.append(K >= 2 and len(seen) >= need)
    return torch.tensor(out)


@pytest.mark.parametrize("frac", [0.0, 0.5, 0.75, 1.0])
def test_split_static_matches_bruteforce(frac):
    gen = torch.Generator().manual_seed(1)
    pts = torch.rand(300, 3, generator=gen) * 2
    kf = torch.randint(0, 5, (300,), generator=gen)
    got = split_static(pts, kf, 0.4, frac)
    assert torch.equal(got, _split_static_bruteforce(pts, kf, 0.4, frac))
    assert 0 < int(got.sum()) < 300 or frac == 0.0


def test_split_static_needs_two_keyframes():
    pts = torch.rand(20, 3)
    assert not split_static(pts, torch.zeros(20, dtype=torch.int64), 0.1).any()


def _scene_points(K=6, n_static=400, n_moving=60, seed=0):
    """A static plane seen (with noise) at every keyframe and a small cube moving along x."""
    gen = torch.Generator().manual_seed(seed)
    grid = torch.stack(torch.meshgrid(torch.linspace(0, 2, 20), torch.linspace(0, 2, 20), indexing="ij"), -1)
    plane = torch.cat([grid.reshape(-1, 2), torch.zeros(n_static, 1)], 1)
    pts, kf, moving = [], [], []
    for k in range(K):
        pts.append(plane + 0.002 * torch.randn(plane.shape, generator=gen))
        kf.append(torch.full((n_static,), k))
        moving.append(torch.zeros(n_static, dtype=torch.bool))
        cube = torch.rand(n_moving, 3, generator=gen) * 0.2 + torch.tensor([0.3 * k, 1.0, 0.5])
        pts.append(cube)
        kf.append(torch.full((n_moving,), k))
        moving.append(torch.ones(n_moving, dtype=torch.bool))
    return torch.cat(pts), torch.cat(kf), torch.cat(moving)


def _model(layout, K=6, F=31):
    m, _ = preset("tiny")
    m.anchor_layout, m.window, m.voxel_size = layout, 3, 0.1
    pts, kf, _ = _scene_points(K)
    cam = side_camera(eye=(1.0, -4, 1.0), target=(1.0, 1.0, 0.5))
    return ATGSModel.from_points(m, pts, kf, evenly_spaced(F, K), F, 25.0, [cam], seed=0)


def test_split_layout_models_static_content_once():
    pts, kf, moving = _scene_points()
    assert torch.equal(split_static(pts, kf, 0.2, 0.5), ~moving), "the plane is static, the cube is not"
    split, per_kf = _model("split"), _model("per-keyframe")
    static = split.anchor_keyframe == STATIC
    # the plane once (about its 21x21 voxel cells), the cube at each of its 6 keyframes
    assert 300 <= int(static.sum()) <= 500
    assert (split.anchor_mu[static][:, 2].abs() < 0.06).all()
    n_static_per_kf = int(((per_kf.anchor_mu[:, 2].abs() < 0.06)).sum())
    assert n_static_per_kf > 5 * int(static.sum()), "per-keyframe layout repeats the plane per keyframe"
    assert split.num_anchors < per_kf.num_anchors / 3
    moving_split = split.anchor_mu[~static]
    assert (moving_split[:, 2] > 0.3).all(), "only the cube gets per-keyframe anchors"
    # static anchors are active at every frame; moving anchors follow the window
    for f in range(split.num_frames):
        act = split.active_anchors(f)
        assert act[static].all()
        lo, hi = split.timeline.window_of_frame(f)
        k = split.anchor_keyframe
        assert torch.equal(act[~static], ((k >= lo) & (k <= hi))[~static])
    # fewer Gaussians decoded per frame as well
    assert len(split.gaussians_at_frame(15)) < len(per_kf.gaussians_at_frame(15))


def test_split_layout_random_anchors_are_static():
    m, _ = preset("tiny")
    m.random_anchors = 50
    pts, kf, _ = _scene_points()
    cam = _model("split").cameras
    model = ATGSModel.from_points(m, pts, kf, [0, 6, 12, 18, 24, 30], 31, 25.0, cam, seed=0)
    assert int((model.anchor_keyframe == STATIC).sum()) >= 300
    m.anchor_layout = "bogus"
    with pytest.raises(ValueError, match="anchor_layout"):
        ATGSModel.from_points(m, pts, kf, [0, 6, 12, 18, 24, 30], 31, 25.0, cam, seed=0)


def test_prune_final_drops_faint_and_unseen_anchors():
    model = _model("split")
    q, A = model.cfg.gaussians_per_anchor, model.num_anchors
    cfg = DensifyConfig(min_opacity=0.01)
    stats = DensifyStats.zeros(A, q)
    stats.anchor_count[:] = 10
    stats.opacity_accum[:] = 10 * 0.5  # bright
    stats.opacity_accum[:5] = 10 * 0.001  # faint
    stats.anchor_count[5:8] = 0  # never decoded in view
    stats.opacity_accum[5:8] = 0
    mu_kept_expected = torch.cat([model.anchor_mu[8:]])
    # not enough steps to trust "never seen": only the faint ones go
    m1 = _model("split")
    n = prune_final(m1, DensifyStats.from_state(stats.state_dict()), cfg, None, prune_unseen=False)
    assert n == 5 and m1.num_anchors == A - 5
    n = prune_final(model, stats, cfg, None, prune_unseen=True)
    assert n == 8 and model.num_anchors == A - 8
    torch.testing.assert_close(model.anchor_mu, mu_kept_expected)
    # never everything
    stats = DensifyStats.zeros(model.num_anchors, q)
    assert prune_final(model, stats, cfg, None, prune_unseen=True) == 0


def test_training_prunes_anchors_outside_every_view(tmp_path):
    """Anchors placed where no training camera looks are removed at the end of training."""
    from builders import make_toy_scene
    from atgs.train.trainer import Trainer

    scene = make_toy_scene(num_frames=5, num_cameras=4, width=32, height=24, keyframes=3)
    m, t = preset("tiny")
    t.iterations, t.densify.enabled = 60, False
    tr = Trainer(scene, m, t, tmp_path)
    far = tr.model.anchor_mu[:4] + 1000.0  # far behind/outside every camera
    tr.model.add_anchors(far, torch.zeros(4, m.feature_dim), tr.model.anchor_log_scale[:4].clone(),
                         torch.full((4,), STATIC))
    tr.stats.append(4, m.gaussians_per_anchor)
    from atgs.model.atgs_model import ANCHOR_TABLES

    for name in ANCHOR_TABLES:
        tr.sparse_opt.append_rows(name, 4)
    tr.model.refresh_reach()  # as the trainer does for anchors it adds: measured before any decode
    n0 = tr.model.num_anchors
    need = 2 * len(tr.train_idx) * tr.model.num_keyframes
    t.iterations = max(60, need)
    res = tr.train(progress=False, final_renders=False)
    assert res["final_pruned"] >= 4
    d = (tr.model.anchor_mu[:, None, :] - far[None]).norm(dim=-1)
    assert (d > 1.0).all(), "the out-of-view anchors are gone"
    assert tr.model.num_anchors <= n0 - 4


def test_static_voxel_factor_downsamples_static_points_finer():
    from atgs.model.anchors import init_anchors, voxel_downsample

    pts, kf, moving = _scene_points()
    kf = torch.where(moving, kf, torch.full_like(kf, STATIC))
    for factor in (1.0, 0.5):
        a = init_anchors(pts, kf, voxel_size=0.1, static_voxel_factor=factor)
        static = a.keyframe == STATIC
        want = voxel_downsample(pts[~moving], 0.1 * factor)  # the static points at the finer voxel
        assert int(static.sum()) == want.shape[0]
        torch.testing.assert_close(a.mu[static].sort(0).values, want.sort(0).values)
        for k in range(6):  # per-keyframe anchors keep the base voxel
            assert int((a.keyframe == k).sum()) == voxel_downsample(pts[moving & (kf == k)], 0.1).shape[0]
