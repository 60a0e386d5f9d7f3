"""Stability at the extremes (issue 6): time, geometry through model -> rasterizer, reduced
precision decoding, non-finite values during training.

Covered elsewhere (not repeated here): the exact frame <-> keyframe mapping of 10,000 frames and
time validation (tests/test_timeline.py), rasterizer extremes on raw Gaussians
(tests/test_render_edge_cases.py), a NaN/inf loss leaving every parameter unchanged and the
consecutive-bad-steps stop, and NaN decoder gradients being zeroed (tests/test_train_e2e.py).
"""

from __future__ import annotations

import csv
import math
from dataclasses import replace

import pytest
import torch

from atgs.cameras import Camera
from atgs.gaussians import Gaussians
from atgs.model import precision
from atgs.model.anchors import STATIC
from atgs.model.atgs_model import ATGSModel
from atgs.train.config import preset
from atgs.render import rasterize_gaussians
import atgs.train.trainer as trainer_mod
from builders import make_toy_scene, random_point_model, ring_cameras, tiny_config
from atgs.train.trainer import Trainer


def cameras(n: int = 3, size: tuple[int, int] = (32, 24)) -> list[Camera]:
    return ring_cameras(n, size)


def build(F: int = 9, K: int = 3, M: int = 2, W: int = 3, n: int = 120, cull: bool = False,
          opacity_threshold: float = 0.0, randomize: bool = True, seed: int = 0) -> ATGSModel:
    """A tiny model through the package API with non-trivial features (builders.random_point_model)."""
    cfg = tiny_config(K, W, M, hidden=16, frustum_cull=cull, opacity_threshold=opacity_threshold)
    return random_point_model(cfg, F, n, cameras(), seed=seed, randomize=randomize)


def assert_finite(g: Gaussians, what: str) -> None:
    for name, x in zip(("means", "quats", "scales", "opacities", "colors"), g.as_tuple()):
        assert torch.isfinite(x).all(), f"{what}: non-finite {name}"


def assert_same(a: Gaussians, b: Gaussians, what: str) -> None:
    for x, y in zip(a.as_tuple(), b.as_tuple()):
        assert torch.equal(x, y), what


# --- time -------------------------------------------------------------------------------------
TIME_CASES = {  # name: (F, K, M, W)
    "default": (9, 3, 2, 3),
    "K=1": (9, 1, 2, 3),
    "M=1": (9, 3, 1, 3),
    "W=1": (9, 3, 2, 1),
    "W>K": (9, 3, 2, 7),
    "W=0 (no window)": (9, 3, 2, 0),
    "M>F": (3, 2, 8, 3),
    "F=1": (1, 1, 2, 3),
    "F=10000": (10_000, 5, 4, 3),
}


@pytest.mark.parametrize("case", list(TIME_CASES))
def test_time_extremes_decode_finite_and_clamped(case: str) -> None:
    F, K, M, W = TIME_CASES[case]
    model = build(F, K, M, W)
    assert (model.num_frames, model.num_keyframes, model.num_segments) == (F, K, M)
    frames = range(F) if F <= 50 else sorted({0, 1, 2499, 2500, F // 2, F - 2, F - 1})
    for f in frames:
        g = model.gaussians_at_frame(f)
        assert len(g) > 0, f"{case}: frame {f} decodes no Gaussian"
        assert_finite(g, f"{case} frame {f}")
        mask = model.active_anchors(f)
        kbar = model.timeline.nearest_keyframe_of_frame(f)
        k = model.anchor_keyframe
        if W == 0 or W // 2 >= K - 1:  # window covers every keyframe
            assert mask.all(), case
        if W == 1:  # only the nearest keyframe (and the always-active static anchors)
            assert torch.equal(mask, (k == kbar) | (k == STATIC)), case
    first, last = model.gaussians_at_frame(0), model.gaussians_at_frame(F - 1)
    assert_same(model.gaussians_at(0.0), first, f"{case}: t=0 is frame 0")
    for t in (-1e-7, -0.5, -1e30, -math.inf):
        assert_same(model.gaussians_at(t), model.gaussians_at(0.0), f"{case}: t={t} clamps to 0")
    for t in (1 + 1e-7, 1.5, 1e30, math.inf):
        assert_same(model.gaussians_at(t), model.gaussians_at(1.0), f"{case}: t={t} clamps to 1")
    end = model.gaussians_at(1.0)
    assert_finite(end, case)
    if F > 1:
        assert_same(end, last, f"{case}: t=1 is the last frame")
    near = model.gaussians_at(1 - 1e-7)
    assert_finite(near, f"{case} t=1-1e-7")
    assert len(near) == len(end)  # same frame, so same window and segment
    for x, y in zip(near.as_tuple(), end.as_tuple()):  # the local time differs by M * 1e-7 only
        assert torch.allclose(x, y, atol=1e-4, rtol=0), case


# --- geometry through decode + rasterize, forward and backward -------------------------------
def render_backward(model: ATGSModel, cam: Camera, backend: str, frame: int = 4) -> tuple[Gaussians, torch.Tensor]:
    """Tracked decode, rasterize, loss, backward; every output and gradient must be finite."""
    model.decoder.zero_grad(set_to_none=True)
    dec = model.decode_frame(frame, cam, track=True)
    g = dec.gaussians
    assert len(g) > 0
    out = rasterize_gaussians(g, cam, background=torch.tensor([0.2, 0.3, 0.4]), backend=backend)
    out.means2d.retain_grad()
    target = torch.rand(out.image.shape, generator=torch.Generator().manual_seed(0))
    # the trainer's terms: L1 image loss and the volume regularizer (1e12 per Gaussian at scale 1e4)
    loss = (out.image - target).abs().mean() + 1e-3 * g.scales.prod(dim=1).mean() + out.alpha.mean()
    loss.backward()
    assert torch.isfinite(out.image).all() and torch.isfinite(out.alpha).all(), "non-finite render"
    assert torch.isfinite(loss), "non-finite loss"
    if out.means2d.grad is not None:
        assert torch.isfinite(out.means2d.grad).all(), "non-finite means2d gradient"
    n_grads = 0
    for s in dec.sparse:
        if s.leaf.grad is not None:
            assert torch.isfinite(s.leaf.grad).all(), f"non-finite gradient of {s.name}"
            n_grads += 1
    for name, p in model.decoder.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), f"non-finite gradient of decoder {name}"
    assert n_grads >= 3, "gradients reach the sparse tables"
    return g, out.image.detach()


def _small_scale(model: ATGSModel, rows: torch.Tensor | slice = slice(None)) -> None:
    model.anchor_log_scale[rows, :3] = math.log(1e-3)  # offsets barely move means off the anchor


GEOMETRY_CASES = ("bounds", "scale 1e-8", "scale 1e4", "camera inside", "opacity ~1", "zero quats")


@pytest.mark.parametrize("backend", ["cpu", "torch"])
@pytest.mark.parametrize("case", GEOMETRY_CASES)
def test_geometry_extremes_forward_backward_finite(case: str, backend: str) -> None:
    model = build(n=60)
    cam = model.cameras[0]
    if case == "bounds":  # anchors exactly on the grid bounds and far outside
        lo, hi = model.bbox_min, model.bbox_max
        model.anchor_mu[:4] = torch.stack([lo, hi, torch.stack([lo[0], hi[1], lo[2]]), (lo + hi) / 2])
        model.anchor_mu[4:8] = torch.stack([hi + 0.5, lo - 0.5, hi + 1e6, torch.tensor([0.0, 0.0, 1e30])])
    elif case == "scale 1e-8":
        model.anchor_log_scale[:] = math.log(1e-8)
    elif case == "scale 1e4":
        model.anchor_log_scale[:] = math.log(1e4)  # huge Gaussians, offsets up to ~1e4 ...
        _small_scale(model, slice(0, None, 2))  # ... and huge Gaussians at their anchors
    elif case == "camera inside":  # a large Gaussian around the camera centre
        # a free viewpoint (the player's), halfway between cam00 and the scene: the rig cameras'
        # own centres are inside their clearance (atgs.geometry.clearance), which drops such Gaussians
        eye = 0.5 * cam.center + 0.5 * model.anchor_mu.median(0).values.double().numpy()
        w2c = cam.w2c.copy()
        w2c[:3, 3] = -cam.R @ eye
        cam = replace(cam, name="free", w2c=w2c)
        assert model.clearance.outside(torch.from_numpy(eye).float()[None]).all()
        model.anchor_mu[:3] = torch.from_numpy(cam.center).float()
        model.anchor_log_scale[:3, 3:] = math.log(2.0)
        _small_scale(model, slice(0, 3))
        model.anchor_keyframe[:3] = 0  # active at every frame
    elif case == "opacity ~1":
        with torch.no_grad():
            model.decoder.opacity[2].bias.fill_(30.0)  # sigmoid(30) == 1.0 in float32
    elif case == "zero quats":
        with torch.no_grad():
            rows = torch.tensor([s * 7 + c for s in range(model.cfg.gaussians_per_anchor) for c in range(3, 7)])
            model.decoder.cov[2].weight[rows] = 0.0
            model.decoder.cov[2].bias[rows] = 0.0
    g, _ = render_backward(model, cam, backend)
    if case == "opacity ~1":
        assert (g.opacities == 1.0).all()
    if case == "zero quats":
        assert (g.quats == 0).all()
    if case == "scale 1e-8":
        assert g.scales.max() <= 1e-8
    if case == "scale 1e4":
        assert g.scales.max() > 1e3
    if case == "camera inside":
        inside = (g.means - torch.from_numpy(cam.center).float()).norm(dim=1) < 0.01
        assert inside.sum() >= 3 and (g.scales[inside] > 0.1).all()


def test_anchors_outside_grid_bounds_get_zero_grid_features() -> None:
    model = build(n=60)
    lo, hi = model.bbox_min, model.bbox_max
    model.anchor_mu[:4] = torch.stack([lo, hi, hi + 0.5, lo - torch.tensor([0.0, 0.0, 1e-3])])
    model.anchor_keyframe[:4] = 0
    xn = model.normalized_positions(model.anchor_mu[:4])
    fs, _ = model.spatial.query(xn, track=False)
    assert fs[:2].abs().sum() > 0, "anchors on the bounds read the grid"
    assert torch.equal(fs[2:], torch.zeros_like(fs[2:])), "anchors outside read zero F_s features"

    def raw(m: ATGSModel) -> torch.Tensor:
        with torch.no_grad():
            d = m.decode_frame(0, None, track=False)
        ids = d.active
        sel = torch.stack([(ids == i).nonzero().squeeze() for i in range(4)])
        return torch.cat([d.raw.means[sel].flatten(1), d.raw.colors[sel].flatten(1), d.raw.opacities[sel]], 1)

    before = raw(model)
    model.spatial.table = model.spatial.table + 1.0  # change both grids everywhere
    model.hash.table = model.hash.table + 1.0
    after = raw(model)
    assert torch.isfinite(before).all() and torch.isfinite(after).all()
    assert not torch.allclose(before[:2], after[:2]), "anchors on the bounds depend on the grids"
    assert torch.equal(before[2:], after[2:]), "anchors outside the bounds do not depend on the grids"
    # and no gradient flows from outside anchors into the grids
    model.anchor_keyframe[4:] = 1
    model.anchor_mu[4:] = hi + 1.0
    dec = model.decode_frame(model.num_frames - 1, None, track=True)
    outside = ~((model.normalized_positions(model.anchor_mu[dec.active]) >= 0)
                & (model.normalized_positions(model.anchor_mu[dec.active]) <= 1)).all(1)
    assert outside.sum() > 0
    dec.raw.means[outside].sum().add(dec.raw.colors[outside].sum()).backward()
    for s in dec.sparse:
        if s.name in ("spatial", "hash"):
            assert s.leaf.grad is None or not s.leaf.grad.any(), f"{s.name} got a gradient from outside anchors"


def test_anchor_init_from_degenerate_point_sets_is_finite() -> None:
    from atgs.model.anchors import init_anchors

    for pts in (torch.zeros(1, 3), torch.zeros(4, 3), torch.tensor([[0.0, 0, 0], [1e-7, 0, 0]]),
                torch.tensor([[0.0, 0, 0], [1.0, 0, 0]]), torch.tensor([[0.0, 0, 0], [1e4, 0, 0]])):
        a = init_anchors(pts, torch.zeros(len(pts), dtype=torch.int64))
        assert a.mu.shape[0] >= 1 and torch.isfinite(a.mu).all() and torch.isfinite(a.log_scale).all(), pts


# --- precision -----------------------------------------------------------------------------------
# Tolerances against float32 (measured maxima over all frames of this model and of a model with
# the "cpu" preset's decoder sizes, in docs/model.md "Precision"; tolerances ~3x the measured):
# means in units of the Gaussian's own largest scale, scales relative, quaternion components,
# opacity and colour absolute.
IMAGE_MIN_PSNR = {torch.bfloat16: 50.0, torch.float16: 70.0}  # dB against the float32 render
IMAGE_MAX_ERROR = {torch.bfloat16: 8 / 255, torch.float16: 1 / 255}  # at any pixel
TOLERANCES = {
    torch.bfloat16: {"means": 5e-2, "quats": 1e-1, "scales": 1e-2, "opacities": 3e-3, "colors": 3e-3},
    torch.float16: {"means": 6e-3, "quats": 3e-2, "scales": 1.5e-3, "opacities": 4e-4, "colors": 4e-4},
}


def precision_errors(a: Gaussians, b: Gaussians) -> dict[str, float]:
    s = a.scales.max(dim=1).values
    return {"means": float(((a.means - b.means).norm(dim=1) / s).max()),
            "quats": float((a.quats - b.quats).abs().max()),
            "scales": float(((a.scales - b.scales).abs() / a.scales).max()),
            "opacities": float((a.opacities - b.opacities).abs().max()),
            "colors": float((a.colors - b.colors).abs().max())}


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_reduced_precision_decode_within_tolerance(dtype: torch.dtype) -> None:
    model = build(n=200)
    ref_params = {k: v.clone() for k, v in model.decoder.state_dict().items()}
    view = precision.low_precision_view(model, dtype)
    assert all(p.dtype == dtype for p in view.decoder.parameters())
    worst = dict.fromkeys(TOLERANCES[dtype], 0.0)
    for f in range(model.num_frames):
        a, b = model.gaussians_at_frame(f), view.gaussians_at_frame(f)
        assert len(a) == len(b) and all(x.dtype == torch.float32 for x in b.as_tuple())
        assert_finite(b, f"{dtype} frame {f}")
        for k, e in precision_errors(a, b).items():
            worst[k] = max(worst[k], e)
    for k, tol in TOLERANCES[dtype].items():
        assert worst[k] <= tol, f"{dtype}: {k} error {worst[k]:.2e} > {tol:.0e}"
    assert worst["colors"] > 0, "the reduced-precision path is actually used"
    # the rendered image stays close to float32 (bf16 moves sharp edges by a fraction of a pixel)
    cam = model.cameras[0]
    img = [rasterize_gaussians(g, cam, backend="cpu").image
           for g in (model.gaussians_at(0.5), precision.gaussians_at(model, 0.5, dtype))]
    diff = img[0] - img[1]
    assert 10 * math.log10(1.0 / max(float(diff.pow(2).mean()), 1e-20)) > IMAGE_MIN_PSNR[dtype]
    assert diff.abs().max() < IMAGE_MAX_ERROR[dtype]
    # the model itself is untouched and keeps decoding in float32
    for k, v in model.decoder.state_dict().items():
        assert v.dtype == torch.float32 and torch.equal(v, ref_params[k]), k
    assert_same(precision.gaussians_at_frame(model, 3, dtype), view.gaussians_at_frame(3), "deterministic")


def test_reduced_precision_rejects_other_dtypes() -> None:
    with pytest.raises(ValueError, match="dtype"):
        precision.low_precision_view(build(n=20), torch.float64)


# --- training with injected non-finite values ----------------------------------------------------
def test_training_survives_injected_nan_loss_and_inf_gradient(tmp_path, monkeypatch) -> None:  # noqa: ANN001
    scene = make_toy_scene(num_frames=4, num_cameras=3, width=24, height=16, keyframes=2)
    m, t = preset("tiny")
    t.iterations, t.max_bad_steps = 10, 2
    t.densify.start, t.densify.interval = 2, 3  # densify after the injected steps see the statistics
    real = trainer_mod.rasterize_gaussians
    calls = {"n": 0}

    def faulty(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        out = real(*args, **kwargs)
        calls["n"] += 1
        if calls["n"] == 3:  # a NaN image: the loss is NaN, the step must be skipped
            out.image = out.image * float("nan")
        elif calls["n"] == 5:  # a finite loss whose gradient is inf
            out.image.register_hook(lambda g: torch.full_like(g, float("inf")))
        return out

    monkeypatch.setattr(trainer_mod, "rasterize_gaussians", faulty)
    tr = Trainer(scene, m, t, tmp_path)
    densify = tr._maybe_densify

    def checked_densify() -> None:  # the statistics densification reads stay finite at every step
        for name, v in tr.stats.state_dict().items():
            assert torch.isfinite(v).all(), f"step {tr.step}: non-finite densification statistic {name}"
        densify()

    monkeypatch.setattr(tr, "_maybe_densify", checked_densify)
    result = tr.train(progress=False, final_renders=True)
    assert calls["n"] >= 10
    assert result["steps"] == 10 and result["skipped"] == 1 and tr.skipped == 1
    rows = list(csv.DictReader(open(tmp_path / "train_log.csv")))
    assert [int(r["skipped"]) for r in rows] == [0, 0, 1, 1, 1, 1, 1, 1, 1, 1]
    assert math.isnan(float(rows[2]["loss"])) and math.isfinite(float(rows[4]["loss"]))
    for name, v in tr.model.sparse_tensors().items():
        assert torch.isfinite(v).all(), f"non-finite {name} after training"
    for name, p in tr.model.decoder.named_parameters():
        assert torch.isfinite(p).all(), f"non-finite decoder {name} after training"
    for name, v in tr.stats.state_dict().items():
        assert torch.isfinite(v).all(), f"non-finite densification statistic {name}"
    for state in tr.dense_opt.state.values():
        assert all(torch.isfinite(x).all() for x in state.values() if torch.is_tensor(x))
    assert_finite(tr.model.gaussians_at(0.5), "after training")
    assert math.isfinite(result["eval"]["psnr"])
