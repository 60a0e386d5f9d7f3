"""End-to-end training on a toy scene; non-finite handling."""

import csv
import json

import pytest
import torch

from atgs.train.config import preset
from builders import make_toy_scene
from atgs.train.trainer import NonFiniteError, Trainer


@pytest.fixture(scope="module")
def scene():
    return make_toy_scene(num_frames=6, num_cameras=5, width=40, height=32, keyframes=3)


def test_loss_decreases_on_toy_scene(scene, tmp_path):
    m, t = preset("tiny")
    t.iterations = 60
    t.eval_max_frames = 2
    before = Trainer(scene, m, t, tmp_path / "x").evaluate()
    tr = Trainer(scene, m, t, tmp_path)
    result = tr.train(progress=False)
    rows = list(csv.DictReader(open(tmp_path / "train_log.csv")))
    assert len(rows) == 60
    first = sum(float(r["loss"]) for r in rows[:10]) / 10
    last = sum(float(r["loss"]) for r in rows[-10:]) / 10
    assert last < 0.7 * first, (first, last)
    assert result["eval"]["psnr"] > before["psnr"] + 1.0
    assert (tmp_path / "ckpt.pt").is_file()
    # the final evaluation is atgs-eval's default: every frame of each test camera at full
    # resolution, three comparison images per camera, the same mean PSNR
    n_test = len(scene.test_indices)
    assert result["eval"]["views"] == scene.num_frames * n_test
    assert len(list((tmp_path / "eval" / "images").rglob("*.png"))) == 3 * n_test
    assert json.loads((tmp_path / "eval" / "summary.json").read_text())["num_views"] == result["eval"]["views"]
    from atgs.eval.evaluate import EvalConfig, evaluate

    again = evaluate(tr.model, scene, EvalConfig(lpips=False, progress=False, images_per_camera=0), None,
                     background=t.background)
    assert abs(again.mean("psnr") - result["eval"]["psnr"]) < 1e-6


def test_nonfinite_loss_skips_step_and_keeps_state(scene, tmp_path):
    m, t = preset("tiny")
    t.iterations, t.max_bad_steps = 20, 3
    tr = Trainer(scene, m, t, tmp_path)
    for _ in range(3):
        tr.train_step()
    snap = {k: v.clone() for k, v in tr.model.sparse_tensors().items()}
    dec_snap = {k: v.clone() for k, v in tr.model.decoder.state_dict().items()}
    real = tr.compute_loss
    tr.compute_loss = lambda dec, out, gt: real(dec, out, gt) * float("nan")
    r = tr.train_step()
    assert r.skipped and tr.skipped == 1
    for k, v in tr.model.sparse_tensors().items():
        assert torch.equal(v, snap[k]), k
    for k, v in tr.model.decoder.state_dict().items():
        assert torch.equal(v, dec_snap[k]), k
    tr.compute_loss = real
    assert not tr.train_step().skipped, "training continues after a bad step"
    tr.compute_loss = lambda dec, out, gt: real(dec, out, gt) * float("inf")
    with pytest.raises(NonFiniteError, match="consecutive"):
        for _ in range(5):
            tr.train_step()


def test_nonfinite_gradients_are_zeroed(scene, tmp_path):
    m, t = preset("tiny")
    tr = Trainer(scene, m, t, tmp_path)
    head = tr.model.decoder.color[2]
    hook = head.weight.register_hook(lambda g: torch.full_like(g, float("nan")))
    w0 = head.weight.detach().clone()
    tr.train_step()
    hook.remove()
    assert torch.isfinite(head.weight).all()
    assert torch.equal(head.weight, w0), "a NaN gradient is zeroed, so Adam does not move the weight"
    assert all(torch.isfinite(v).all() for v in tr.model.sparse_tensors().values())


def test_view_without_gaussians_is_harmless(scene, tmp_path):
    m, t = preset("tiny")
    tr = Trainer(scene, m, t, tmp_path)
    tr.model.anchor_mu += 100.0  # every anchor far outside every camera frustum
    before = tr.model.anchor_feature.clone()
    r = tr.train_step()
    assert not r.skipped and r.gaussians == 0
    assert torch.equal(tr.model.anchor_feature, before)
