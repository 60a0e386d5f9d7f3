"""Anchor growing and pruning on hand-made statistics."""

import math

import torch

from atgs.model.anchors import AnchorInit
from atgs.model.atgs_model import ATGSModel
from atgs.train.config import DensifyConfig, preset
from atgs.timeline import Timeline
from atgs.train.densify import DensifyStats, grow_anchors, prune_anchors
from atgs.train.optim import SparseAdam


def _model(n=4):
    m, _ = preset("tiny")
    mu = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])[:n]
    a = AnchorInit(mu, torch.full((n, 6), -2.0), torch.tensor([0, 1, 1, 2])[:n], voxel_size=0.01)
    model = ATGSModel(m, Timeline(10, 3, 3, 1), [], 30.0, a, torch.full((3,), -1.0), torch.full((3,), 2.0), 1.0)
    model.anchor_feature = torch.arange(n * m.feature_dim, dtype=torch.float32).view(n, -1)
    return model


def test_growing_adds_anchor_in_empty_voxel_with_parent_keyframe_and_max_feature():
    model = _model()
    q = model.cfg.gaussians_per_anchor
    cfg = DensifyConfig(interval=10, grad_threshold=1e-3, levels=1, init_factor=16, hierarchy_factor=4,
                        success_threshold=0.8)
    opt = SparseAdam(model.sparse_tensors())
    stats = DensifyStats.zeros(model.num_anchors, q)
    size = 0.01 * 16
    target = torch.tensor([0.5, 0.5, 0.5])
    # two slots of anchors 1 and 2 (keyframe 1) land in the same empty voxel with high gradients
    for s in (1 * q + 0, 2 * q + 1):
        stats.grad_accum[s], stats.grad_count[s] = 1.0, 10.0
        stats.last_pos[s] = target + 0.01
    # a slot with a high gradient in the voxel of an existing anchor of the same keyframe: no growth
    stats.grad_accum[3 * q], stats.grad_count[3 * q] = 1.0, 10.0
    stats.last_pos[3 * q] = torch.tensor([0.0, 0.0, 1.0])
    # a low-gradient slot: no growth
    stats.grad_accum[0], stats.grad_count[0] = 1e-5, 10.0
    stats.last_pos[0] = torch.tensor([-0.5, -0.5, -0.5])
    # levels=1 thins candidates with rand > 0.5: use a generator state that keeps them
    for seed in range(100):
        g = torch.Generator().manual_seed(seed)
        keep = torch.rand(model.num_anchors * q, generator=g) > 0.5
        if keep[q] and keep[2 * q + 1]:
            break
    n = grow_anchors(model, stats, cfg, opt, torch.Generator().manual_seed(seed))
    assert n == 1 and model.num_anchors == 5
    expected = torch.round(target / size) * size
    torch.testing.assert_close(model.anchor_mu[4], expected)
    assert model.anchor_keyframe[4] == 1
    torch.testing.assert_close(model.anchor_feature[4], torch.maximum(model.anchor_feature[1], model.anchor_feature[2]))
    torch.testing.assert_close(model.anchor_log_scale[4], torch.full((6,), math.log(size)))
    assert opt.exp_avg["anchor_feature"].shape[0] == 5 and stats.opacity_accum.shape[0] == 5
    assert stats.grad_accum.shape[0] == 5 * q and stats.grad_accum[q] == 0, "statistics reset after growing"


def test_pruning_removes_transparent_anchors_only_after_enough_visits():
    model = _model()
    q = model.cfg.gaussians_per_anchor
    cfg = DensifyConfig(interval=10, min_opacity=0.05, success_threshold=0.8)
    opt = SparseAdam(model.sparse_tensors())
    opt.exp_avg["anchor_feature"][2] = 7.0
    stats = DensifyStats.zeros(4, q)
    stats.anchor_count[:] = torch.tensor([20.0, 20.0, 20.0, 3.0])  # anchor 3 not seen enough
    stats.opacity_accum[:] = torch.tensor([0.01 * 20, 0.5 * 20, 0.2 * 20, 0.0])
    feats = model.anchor_feature.clone()
    n = prune_anchors(model, stats, cfg, opt)
    assert n == 1 and model.num_anchors == 3
    torch.testing.assert_close(model.anchor_feature, feats[1:])
    assert opt.exp_avg["anchor_feature"][1, 0] == 7.0, "optimizer rows follow their anchors"
    assert stats.anchor_count.tolist() == [0.0, 0.0, 3.0]


def test_record_accumulates_visible_gaussians():
    model = _model()
    q = model.cfg.gaussians_per_anchor
    stats = DensifyStats.zeros(4, q)
    dec = model.decode_frame(0, track=False)
    n = len(dec.gaussians)
    grad = torch.ones(n, 2)
    radii = torch.ones(n, dtype=torch.int32)
    radii[0] = 0
    stats.record(dec, grad, radii, width=20, height=10, q=q)
    slots = dec.anchor_ids * q + dec.slot_ids
    assert stats.grad_count[slots[0]] == 0 and stats.grad_count[slots[1]] == 1
    assert stats.grad_accum[slots[1]].item() == torch.tensor([10.0, 5.0]).norm().item()
    torch.testing.assert_close(stats.opacity_accum[dec.active], dec.raw.opacities.sum(1))


def test_the_statistics_travel_as_flat_buffers_and_rows_that_they_restore_themselves() -> None:
    """What several workers move of the statistics (atgs.train.distributed, the time partition's
    checkpoint parts), against slices of the fields written out by hand."""
    q, g = 3, torch.Generator().manual_seed(0)
    s = DensifyStats(*(torch.rand(shape, generator=g) for shape in ((5 * q,), (5 * q,), (5 * q, 3), (5,), (5,))))
    block = range(1, 4)
    flat = s.flat_sums(block)
    assert torch.equal(flat, torch.cat([s.grad_accum[3:12], s.grad_count[3:12], s.opacity_accum[1:4],
                                        s.anchor_count[1:4]]))
    other = DensifyStats.zeros(5, q)
    other.restore_sums(block, flat)
    assert torch.equal(other.grad_count[3:12], s.grad_count[3:12]) and torch.equal(other.anchor_count[1:4], s.anchor_count[1:4])
    assert not other.grad_count[:3].any() and not other.opacity_accum[4:].any() and not other.last_pos.any()
    assert torch.equal(s.positions(block), s.last_pos[3:12])
    kept = s.last_pos.clone()
    s.set_positions(block, torch.zeros(9, 3))
    assert not s.last_pos[3:12].any() and torch.equal(s.last_pos[:3], kept[:3]) and torch.equal(s.last_pos[12:], kept[12:])
    before = s.state_dict()
    before = {k: v.clone() for k, v in before.items()}
    s.zero_sums(range(4, 5))
    assert not s.grad_accum[12:].any() and not s.anchor_count[4:].any() and torch.equal(s.grad_accum[:12], before["grad_accum"][:12])
    rows = s.rows_from(2)
    assert list(rows) == list(s.state_dict())
    assert all(torch.equal(rows[k], v[2 * q:] if v.shape[0] == 5 * q else v[2:]) for k, v in s.state_dict().items())


def test_the_sparse_optimizer_state_gives_rows_of_its_tables() -> None:
    tables = {"a": torch.rand(6, 2), "b": torch.rand(4)}
    opt = SparseAdam(tables, backend="torch")
    opt.step("a", tables["a"], torch.tensor([1, 4]), torch.rand(2, 2), 0.1)
    state = opt.state_dict()
    assert {k: v.shape[0] for k, v in opt.rows_from("a", 3).items()} == {"exp_avg": 3, "exp_avg_sq": 3, "steps": 3}
    assert torch.equal(opt.rows_from("a", 3)["steps"], torch.tensor([0, 1, 0]))
    kept = SparseAdam.rows_of_state(state, ("a",), torch.tensor([4, 1]))
    assert torch.equal(kept["exp_avg"]["a"], state["exp_avg"]["a"][[4, 1]]) and kept["steps"]["b"] is state["steps"]["b"]
    assert SparseAdam.state_paths("b") == [("exp_avg", "b"), ("exp_avg_sq", "b"), ("steps", "b")]
    assert all(state[key][name] is not None for key, name in SparseAdam.state_paths("a"))
