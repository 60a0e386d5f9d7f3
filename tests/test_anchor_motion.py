"""Anchor motion (atgs.model.anchor_motion): per-anchor fade in time and velocity.

References: the fade and the displacement written out by hand from the module's formulas, the
gradients of both checked against finite differences of the decoded Gaussians, the cached decode
against the training decode, and a checkpoint from before the feature loading as it was trained.
"""

from __future__ import annotations

import math

import pytest
import torch

import atgs
from atgs.checkpoint import read_checkpoint, save_checkpoint
from atgs.model.atgs_model import ATGSModel
from atgs.model.anchor_motion import MIN_FADE, fade_weight, initial_fade, keyframe_distance, max_fade_width
from atgs.timeline import Timeline
from atgs.train.config import preset
from atgs.train.trainer import Trainer
from builders import keyframe_point_model, make_toy_scene, randomize_features

FIELDS = ("means", "quats", "scales", "opacities", "colors")


def _motion_model(fade: bool = True, velocity: bool = True, F: int = 25, K: int = 5, W: int = 3) -> ATGSModel:
    cfg, _ = preset("tiny")
    cfg.window, cfg.num_segments = W, 2
    cfg.temporal_fade, cfg.anchor_velocity = fade, velocity
    cfg.opacity_threshold = 0.0  # keep all q Gaussians of each anchor (compared slot by slot)
    gen = torch.Generator().manual_seed(4)
    model = keyframe_point_model(cfg, F, K, 20, gen)
    randomize_features(model, gen)
    n = model.num_anchors
    model.anchor_velocity = 0.1 * torch.randn(n, 3, generator=gen)
    # widths between 0.2 and 0.9 keyframe intervals (some above the cap of W=3: 1/3)
    model.anchor_fade = torch.log(0.2 + 0.7 * torch.rand(n, 1, generator=gen))
    return model


def test_fade_weight_is_the_gaussian_of_the_keyframe_distance_and_capped():
    d = torch.tensor([0.0, 0.5, -1.0, 2.0])
    w = torch.tensor([[math.log(0.5)]] * 4)
    torch.testing.assert_close(fade_weight(w, d, max_width=1.0), torch.exp(-0.5 * (d / 0.5) ** 2))
    wide = torch.tensor([[math.log(5.0)]] * 4)  # above the cap: acts as the cap
    torch.testing.assert_close(fade_weight(wide, d, max_width=1.0), torch.exp(-0.5 * d ** 2))
    # the cap: the widest fade is at 1/256 at h + 1/2 keyframe intervals (exact keyframe frames)
    tl = Timeline(121, 21, 7, 2)
    cap = max_fade_width(tl)
    assert math.exp(-0.5 * (3.5 / cap) ** 2) == pytest.approx(1 / 256)
    for no_window in (Timeline(121, 21, 0, 2), Timeline(121, 21, 1, 2), Timeline(121, 1, 7, 2)):
        assert max_fade_width(no_window) == math.inf
    assert initial_fade(0.6, tl) == pytest.approx(math.log(0.6))
    assert initial_fade(50.0, tl) == pytest.approx(math.log(cap))


def test_fade_stays_finite_at_extreme_widths():
    d = torch.tensor([0.0, 1e-4, 1.0, -50.0, 0.0, 3.0])
    lw = torch.tensor([[-200.0], [-200.0], [-200.0], [-200.0], [80.0], [80.0]])  # exp: 0 and inf in float32
    lw.requires_grad_(True)
    w = fade_weight(lw, d, max_width=math.inf)
    assert bool(torch.isfinite(w).all())
    assert float(w[0]) == 1.0 and float(w[4]) == 1.0 and float(w[2]) == 0.0 and float(w[5]) == pytest.approx(1.0)
    w.sum().backward()
    assert bool(torch.isfinite(lw.grad).all())


@pytest.mark.parametrize("F,K,W", [(241, 41, 3), (241, 41, 7), (241, 41, 15), (120, 21, 7), (300, 15, 7),
                                   (100, 100, 3), (37, 10, 5), (1000, 250, 7)])
def test_an_anchor_leaving_the_window_has_faded_below_one_level(F, K, W):
    """No popping: at every frame outside an anchor's window, the widest fade allowed weighs it
    below 1/255 (one 8-bit level even at full opacity), whatever the keyframe rounding."""
    tl = Timeline(F, K, W, 2)
    widest = torch.full((K, 1), math.log(1e6))
    kf = torch.arange(K)
    outside_seen = 0
    for f in range(F):
        lo, hi = tl.window_of_frame(f)
        out = (kf < lo) | (kf > hi)
        w = fade_weight(widest, keyframe_distance(tl, f, kf), max_fade_width(tl))
        assert bool((w[out] < MIN_FADE).all()), (f, w[out].max())
        outside_seen += int(out.sum())
    assert outside_seen > 0
    frames = tl.keyframe_frames()
    # the distance is that of the frames: keyframe frame -> 0, the next keyframe's frame -> ~1
    assert float(keyframe_distance(tl, frames[K // 2], kf[K // 2: K // 2 + 1])) == pytest.approx(0.0, abs=1e-6)
    step = (frames[K // 2 + 1] - frames[K // 2]) * (K - 1) / (F - 1)
    assert float(keyframe_distance(tl, frames[K // 2 + 1], kf[K // 2: K // 2 + 1])) == pytest.approx(step, abs=1e-5)


def test_static_anchors_neither_fade_nor_move():
    tl = Timeline(30, 4, 3, 2)
    d = keyframe_distance(tl, 17, torch.tensor([-1, 0, 3]))
    assert float(d[0]) == 0.0 and float(d[1]) > 0 and float(d[2]) < 0


def test_decode_applies_fade_and_velocity_as_written():
    """The decoded Gaussians equal the motion-free decode with opacities times the fade and means
    plus distance x velocity (written out from the formulas, anchor by anchor)."""
    model = _motion_model()
    plain = _motion_model(fade=False, velocity=False)
    for f in (0, 7, 12, 24):
        moved = model.decode_frame(f, track=False)
        base = plain.decode_frame(f, track=False)
        # the faded-out anchors are skipped: compare on the anchors both decoded
        common = torch.isin(base.active, moved.active)
        ids = base.active[common]
        q = model.cfg.gaussians_per_anchor
        kf_frames = torch.tensor(model.timeline.keyframe_frames(), dtype=torch.float32)
        kf = model.anchor_keyframe[ids]
        dist = (f - kf_frames[kf.clamp_min(0)]) * (model.num_keyframes - 1) / (model.num_frames - 1)
        dist = torch.where(kf >= 0, dist, torch.zeros_like(dist))  # static anchors: no motion
        assert bool((kf >= 0).any()) and bool((kf < 0).any())
        width = torch.exp(model.anchor_fade[ids, 0]).clamp(max=max_fade_width(model.timeline))
        fade = torch.exp(-dist ** 2 / (2 * width ** 2))
        torch.testing.assert_close(moved.raw.opacities.reshape(-1, q),
                                   base.raw.opacities.reshape(-1, q)[common], rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(moved.gaussians.opacities.reshape(-1, q),
                                   base.gaussians.opacities.reshape(-1, q)[common] * fade[:, None],
                                   rtol=1e-5, atol=1e-6)
        shift = model.anchor_velocity[ids] * dist[:, None]
        torch.testing.assert_close(moved.gaussians.means.reshape(-1, q, 3),
                                   base.gaussians.means.reshape(-1, q, 3)[common] + shift[:, None, :],
                                   rtol=1e-5, atol=1e-5)
        skipped = base.active[~common]
        if skipped.numel():
            assert bool((model.anchor_keyframe[skipped] >= 0).all())
            d_s = (f - kf_frames[model.anchor_keyframe[skipped]]) * (model.num_keyframes - 1) / (model.num_frames - 1)
            w_s = torch.exp(model.anchor_fade[skipped, 0]).clamp(max=max_fade_width(model.timeline))
            assert bool((torch.exp(-d_s ** 2 / (2 * w_s ** 2)) < model.fade_cut()).all())


def test_fast_decode_equals_training_decode_with_motion():
    model = _motion_model()
    for f in list(range(model.num_frames)) + [3, 0]:
        a, b = model.gaussians_at_frame(f), model.gaussians_at_frame_reference(f)
        for k in FIELDS:
            torch.testing.assert_close(getattr(a, k), getattr(b, k), rtol=1e-5, atol=2e-6, msg=k)


def test_velocity_and_fade_gradients_match_finite_differences():
    torch.manual_seed(0)
    model = _motion_model()
    f = 9
    dec = model.decode_frame(f, track=True)
    g = dec.gaussians
    wm = torch.randn(g.means.shape, dtype=torch.float64)
    wo = torch.randn(g.opacities.shape, dtype=torch.float64)

    def loss(gs) -> torch.Tensor:
        return (gs.means.double() * wm).sum() + (gs.opacities.double() * wo).sum()

    loss(g).backward()
    leaves = {s.name: s for s in dec.sparse}
    for name in ("anchor_velocity", "anchor_fade"):
        leaf = leaves[name]
        table = getattr(model, name)
        # a few anchors that show at this frame, one coordinate each
        for i in range(0, leaf.rows.numel(), max(1, leaf.rows.numel() // 6)):
            row, col = int(leaf.rows[i]), 0
            eps = 1e-3
            vals = []
            for s in (eps, -eps):
                table[row, col] += s
                with torch.no_grad():
                    vals.append(float(loss(model.decode_frame(f, track=False).gaussians)))
                table[row, col] -= s
            fd = (vals[0] - vals[1]) / (2 * eps)
            assert float(leaf.leaf.grad[i, col]) == pytest.approx(fd, rel=2e-2, abs=2e-3), (name, row)


def test_densify_statistics_keep_the_keyframe_position_of_moving_gaussians():
    """Growth places a new anchor where its parent's Gaussian is at the keyframe (the new anchor
    inherits the velocity, so placing it at the displaced position would move it twice)."""
    from atgs.train.densify import DensifyStats

    model = _motion_model()
    q = model.cfg.gaussians_per_anchor
    f = 8  # between keyframes 1 (frame 6) and 2 (frame 12): every moving anchor is displaced
    dec = model.decode_frame(f, track=False)
    moving = model.anchor_keyframe[dec.anchor_ids] >= 0
    assert bool(moving.any()) and dec.shift is not None
    stats = DensifyStats.zeros(model.num_anchors, q)
    n = len(dec.gaussians)
    stats.record(dec, torch.ones(n, 2), torch.ones(n), 32, 24, q)
    slots = dec.anchor_ids * q + dec.slot_ids
    # the reference: the same decode without velocity (positions at the keyframe)
    still = _motion_model(velocity=False).decode_frame(f, track=False)
    assert torch.equal(still.anchor_ids, dec.anchor_ids)
    torch.testing.assert_close(stats.last_pos[slots], still.gaussians.means, rtol=1e-5, atol=1e-5)
    assert float((dec.gaussians.means - still.gaussians.means).detach()[moving].abs().max()) > 1e-3


def test_training_learns_motion_and_resumes(tmp_path):
    scene = make_toy_scene(num_frames=7, num_cameras=4, width=40, height=30, keyframes=3)
    m, t = preset("tiny")
    m.temporal_fade = m.anchor_velocity = True
    t.iterations = 24
    tr = Trainer(scene, m, t, tmp_path / "run")
    fade0 = tr.model.anchor_fade.clone()
    tr.train(progress=False, final_renders=False)
    moving = tr.model.anchor_keyframe >= 0
    assert bool(moving.any())
    assert float(tr.model.anchor_velocity[moving].abs().max()) > 0, "velocities never trained"
    assert not torch.equal(tr.model.anchor_fade[: fade0.shape[0]], fade0), "fades never trained"
    assert float(tr.model.anchor_velocity[~moving].abs().sum()) == 0.0, "static anchors moved"
    loaded = atgs.load(tmp_path / "run" / "ckpt.pt")
    assert loaded.cfg.temporal_fade and loaded.cfg.anchor_velocity
    for fr in range(scene.num_frames):
        a, b = loaded.gaussians_at_frame(fr), tr.model.gaussians_at_frame(fr)
        for x, y in zip(a.as_tuple(), b.as_tuple()):
            assert torch.equal(x, y)


def test_checkpoint_from_before_motion_loads_as_trained(tmp_path):
    """A checkpoint without the motion tables decodes with both off, whatever its config says."""
    scene = make_toy_scene(num_frames=5, num_cameras=4, width=32, height=24, keyframes=3)
    m, t = preset("tiny")
    m.temporal_fade = m.anchor_velocity = False  # trained as before the feature
    t.iterations = 4
    tr = Trainer(scene, m, t, tmp_path / "run")
    tr.train(progress=False, final_renders=False)
    path = tmp_path / "run" / "ckpt.pt"
    data = read_checkpoint(path)
    for name in ("anchor_velocity", "anchor_fade"):
        del data["model"][name]
    data["model_config"]["temporal_fade"] = data["model_config"]["anchor_velocity"] = True  # as if on
    old = tmp_path / "old.pt"
    save_checkpoint(old, data)
    model = atgs.load(old)
    assert not model.has_motion
    for fr in range(scene.num_frames):
        for x, y in zip(model.gaussians_at_frame(fr).as_tuple(), tr.model.gaussians_at_frame(fr).as_tuple()):
            assert torch.equal(x, y)


def test_moving_anchor_learning_rate_factor(tmp_path):
    """--train.lr.moving-anchors scales the learning rates of per-keyframe anchors only, and a
    step with it moves them by that factor more than a step without it (Adam's first step
    moves every entry by its learning rate)."""
    from atgs.model.anchors import STATIC
    from atgs.model.atgs_model import ANCHOR_TABLES

    scene = make_toy_scene(num_frames=7, num_cameras=4, width=40, height=30, keyframes=3)
    m, t = preset("tiny")
    m.temporal_fade = m.anchor_velocity = True
    runs = {}
    for factor in (1.0, 4.0):
        t.lr.moving_anchors = factor
        tr = Trainer(scene, m, t, tmp_path / f"run{factor}")
        moving = tr.model.anchor_keyframe != STATIC
        assert bool(moving.any()) and bool((~moving).any())
        rows = torch.arange(tr.model.num_anchors)
        for name in ANCHOR_TABLES:
            lr = torch.as_tensor(tr.sparse_lr(name, rows, 5000)).expand(len(rows))
            tr.cfg.lr.moving_anchors = 1.0
            base = torch.as_tensor(tr.sparse_lr(name, rows, 5000)).expand(len(rows))
            tr.cfg.lr.moving_anchors = factor
            torch.testing.assert_close(lr[~moving], base[~moving])
            torch.testing.assert_close(lr[moving], factor * base[moving])
        before = tr.model.anchor_feature.clone()
        tr.train_step()
        runs[factor] = (tr.model.anchor_feature - before).abs().amax(dim=1), moving
    (d1, moving), (d4, _) = runs[1.0], runs[4.0]
    stepped = (d1 > 0) & (d4 > 0)
    assert bool((stepped & moving).any()) and bool((stepped & ~moving).any())
    torch.testing.assert_close(d4[stepped & moving], 4 * d1[stepped & moving], rtol=1e-3, atol=1e-9)
    torch.testing.assert_close(d4[stepped & ~moving], d1[stepped & ~moving], rtol=1e-3, atol=1e-9)


@pytest.mark.parametrize("factor", [0.0, -1.0, float("nan")])
def test_moving_anchor_factor_must_be_positive(tmp_path, factor):
    from atgs.errors import UserError

    scene = make_toy_scene(num_frames=4, num_cameras=4, width=32, height=24, keyframes=2)
    m, t = preset("tiny")
    t.lr.moving_anchors = factor
    with pytest.raises(UserError, match="moving-anchors"):
        Trainer(scene, m, t, tmp_path)
