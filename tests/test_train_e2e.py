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
                     background=tr.cfg.background)
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
    tr.compute_loss = lambda *a: real(*a) * float("nan")
    r = tr.train_step()
    assert r.skipped and tr.skipped == 1
    for k, v in tr.model.sparse_tensors().items():
        assert torch.equal(v, snap[k]), k
    for k, v in tr.model.decoder.state_dict().items():
        assert torch.equal(v, dec_snap[k]), k
    tr.compute_loss = real
    assert not tr.train_step().skipped, "training continues after a bad step"
    tr.compute_loss = lambda *a: real(*a) * float("inf")
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


def test_cameras_per_frame_step_equals_the_mean_of_separate_renders(scene, tmp_path):
    """One decode rendered from two cameras (``cameras_per_frame``) gives the decoder the
    gradient of the mean of the two losses, computed here with a separate decode per camera."""
    from atgs.render import rasterize_gaussians

    m, t = preset("tiny")
    m.frustum_cull = False  # the shared decode then holds the same anchors as each separate one
    t.cameras_per_frame, t.grad_clip, t.iterations = 2, 0.0, 10
    tr = Trainer(scene, m, t, tmp_path)
    tr.train_step()  # past the first step: nonzero features
    gen_state, queue = tr.gen.get_state(), list(tr.sampler.queue)
    cams, f = tr.sampler.next_views(2)
    assert len(set(cams)) == 2 and set(cams) <= set(tr.train_idx)
    params = [p for name in tr.model.decoder.HEADS for p in getattr(tr.model.decoder, name).parameters()]
    for p in params:
        p.grad = None  # the first step's gradients are still there
    total = 0.0
    for ci in cams:  # the reference, on the same parameters, before the step changes them
        dec = tr.model.decode_frame(f, tr.cams[ci], track=True)
        out = rasterize_gaussians(dec.gaussians, tr.cams[ci], background=tr.fixed_background)
        total = total + tr.compute_loss(dec, out, tr.images.get(ci, f))
    (total / 2).backward()
    expected = [p.grad.clone() for p in params]
    tr.gen.set_state(gen_state)  # the step draws the same frame and cameras
    tr.sampler.queue = queue
    tr.train_step()
    for p, e in zip(params, expected):
        torch.testing.assert_close(p.grad, e, rtol=1e-4, atol=1e-7)


def test_next_views_draws_distinct_cameras(scene, tmp_path):
    from atgs.train.sampling import SegmentSampler

    m, t = preset("tiny")
    tr = Trainer(scene, m, t, tmp_path)
    s = SegmentSampler(tr.model.timeline, [0, 1, 2, 3], torch.Generator().manual_seed(0))
    for _ in range(20):
        cams, f = s.next_views(3)
        assert len(cams) == len(set(cams)) == 3 and 0 <= f < scene.num_frames
    assert sorted(s.next_views(9)[0]) == [0, 1, 2, 3], "more than there are: every camera once"


def test_background_from_images_is_the_mean_colour_of_a_textured_capture_and_is_saved(scene, tmp_path):
    import numpy as np

    from atgs.checkpoint import read_checkpoint
    from builders import textured_copy

    # textured everywhere (no backdrop): the toy scene's cameras over noise images
    textured = textured_copy(scene)
    frames = textured.frames
    m, t = preset("tiny")
    t.iterations, t.eval_max_frames = 2, 1
    assert t.background_from_images  # the default
    tr = Trainer(textured, m, t, tmp_path)
    # independent reference: the mean over every training camera and every frame (the trainer
    # samples 24 (camera, frame) pairs)
    dense = np.mean([frames[(c, f)].reshape(-1, 3).mean(0) / 255.0
                     for c in textured.train_indices for f in range(scene.num_frames)], axis=0)
    assert np.allclose(tr.cfg.background, dense, atol=0.01), (tr.cfg.background, dense)
    assert torch.allclose(tr.fixed_background, torch.tensor(dense, dtype=torch.float32), atol=0.01)
    tr.train(progress=False, final_renders=False)
    saved = read_checkpoint(tmp_path / "ckpt.pt")["train_config"]["background"]
    assert np.allclose(saved, tr.cfg.background)  # atgs-eval and atgs-view render over the saved colour
    assert t.background == (0.0, 0.0, 0.0)  # the caller's config is not mutated


def test_background_from_images_keeps_a_uniform_backdrop(scene, tmp_path):
    """The toy scene's objects float over black: its backdrop colour, not the mean, is used."""
    import numpy as np

    m, t = preset("tiny")
    tr = Trainer(scene, m, t, tmp_path)
    mean = np.mean([scene.frames[(c, 0)].reshape(-1, 3).mean(0) / 255.0 for c in scene.train_indices], axis=0)
    assert mean.max() > 0.03  # the mean would not be black
    assert max(tr.cfg.background) < 0.01
    t.background_from_images = False
    t.background = (0.2, 0.3, 0.4)
    assert Trainer(scene, m, t, tmp_path / "fixed").cfg.background == (0.2, 0.3, 0.4)


def test_resume_keeps_the_background_the_run_trained_over(scene, tmp_path):
    """A checkpoint from before background_from_images (no such key) resumes over its saved
    colour, not over a newly computed mean."""
    from atgs.checkpoint import read_checkpoint, save_checkpoint

    m, t = preset("tiny")
    t.iterations, t.eval_every = 4, 0
    t.background_from_images, t.background = False, (0.1, 0.2, 0.3)
    Trainer(scene, m, t, tmp_path).train(progress=False, stop_at=2)
    data = read_checkpoint(tmp_path / "ckpt.pt")
    del data["train_config"]["background_from_images"]
    save_checkpoint(tmp_path / "ckpt.pt", data)
    resumed = Trainer.resume(scene, tmp_path / "ckpt.pt", tmp_path)
    assert resumed.cfg.background == (0.1, 0.2, 0.3)
    assert torch.allclose(resumed.fixed_background, torch.tensor([0.1, 0.2, 0.3]))
