"""Per-camera exposure (atgs.train.exposure): gauge, recovery of known gains, training, resume."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from atgs.checkpoint import read_checkpoint
from atgs.data.scene import MemoryScene
from atgs.train.config import preset
from atgs.train.exposure import CameraExposure
from atgs.train.trainer import Trainer
from builders import growing_tiny_config, make_toy_scene


def test_a_uniform_shift_of_every_camera_changes_nothing():
    e = CameraExposure(4, lr=0.1)
    with torch.no_grad():
        e.table.copy_(torch.randn(4, 6, generator=torch.Generator().manual_seed(0)))
    img = torch.rand(5, 6, 3)
    before = [e.apply(img, i) for i in range(4)]
    with torch.no_grad():
        e.table += torch.tensor([0.3, -0.2, 0.1, 0.05, -0.4, 0.2])
    for i in range(4):
        assert torch.allclose(e.apply(img, i), before[i], atol=1e-6)
    gains, biases = e.gains_biases()
    assert torch.allclose(gains.log().mean(0), torch.zeros(3), atol=1e-6)  # the average camera is the identity
    assert torch.allclose(biases.mean(0), torch.zeros(3), atol=1e-6)


def test_recovers_known_gains_and_biases():
    """Targets made from one image with known per-camera gains and biases (their log-gains and
    biases averaging zero): least squares on the exposure alone finds them."""
    gen = torch.Generator().manual_seed(1)
    base = torch.rand(16, 16, 3, generator=gen)
    log_k = torch.tensor([[0.2, 0.1, -0.1], [-0.15, 0.0, 0.05], [-0.05, -0.1, 0.05]])
    c = torch.tensor([[0.02, -0.01, 0.0], [-0.03, 0.02, 0.01], [0.01, -0.01, -0.01]])
    targets = [base * log_k[i].exp() + c[i] for i in range(3)]
    e = CameraExposure(3, lr=0.02)
    for step in range(1500):
        i = step % 3
        loss = ((e.apply(base, i) - targets[i]) ** 2).mean()
        loss.backward()
        e.step(clip=0.0)
    gains, biases = e.gains_biases()
    assert torch.allclose(gains.log(), log_k, atol=5e-3), gains.log()
    assert torch.allclose(biases, c, atol=5e-3), biases


def _brightened(scene: MemoryScene, cam: int, factor: float) -> MemoryScene:
    frames = dict(scene.frames)
    for (ci, f), img in scene.frames.items():
        if ci == cam:
            frames[(ci, f)] = np.clip(img.astype(np.float32) * factor, 0, 255).round().astype(np.uint8)
    return dataclasses.replace(scene, frames=frames)


def test_training_finds_the_camera_exposed_brighter(tmp_path):
    scene = _brightened(make_toy_scene(num_frames=4, num_cameras=5, width=40, height=32, keyframes=2), 1, 1.3)
    m, t = preset("tiny")
    t.iterations, t.eval_every, t.camera_exposure, t.background_from_images = 200, 0, "on", False
    t.lr.exposure = 0.01
    tr = Trainer(scene, m, t, tmp_path)
    tr.run_steps(progress=False)
    gains, _ = tr.exposure.gains_biases()
    slot = tr.train_slot[1]
    others = torch.cat([gains[:slot], gains[slot + 1:]])
    # camera 1 is 1.3x the others: its gain is above every other camera's on every channel
    # (the others' spread is the model's misfit at 200 steps of the tiny preset)
    assert (gains[slot] / others.max(0).values > 1.1).all(), gains


def test_resume_continues_the_exposure_exactly(tmp_path):
    scene = make_toy_scene(num_frames=6, num_cameras=5, width=40, height=32, keyframes=3)

    def config():
        m, t = growing_tiny_config(10)
        t.camera_exposure, t.lr.exposure = "on", 0.01
        return m, t

    full = Trainer(scene, *config(), tmp_path / "full")
    full.train(progress=False, final_renders=False)
    half = Trainer(scene, *config(), tmp_path / "half")
    half.train(progress=False, stop_at=5)
    resumed = Trainer.resume(scene, tmp_path / "half" / "ckpt.pt", tmp_path / "half")
    assert resumed.exposure is not None and torch.equal(resumed.exposure.table, half.exposure.table)
    resumed.train(progress=False, final_renders=False)
    assert not torch.equal(full.exposure.table, torch.zeros_like(full.exposure.table))
    assert torch.equal(full.exposure.table, resumed.exposure.table)


def _textured_rig(factor: float | None) -> MemoryScene:
    """A textured ground and box ray cast (exactly) from 6 cameras on an arc, one frame; the
    keyframe points are back-projected from camera 0's exact depth; camera 1 brightened by
    ``factor``. The last camera is held out."""
    from test_data_mvs import raycast, ring

    cams = ring(6, arc_deg=150.0)
    frames, pts = {}, None
    for ci, cam in enumerate(cams):
        img, depth = raycast(cam)
        frames[(ci, 0)] = img
        if ci == 0:
            v, u = np.nonzero(depth > 0)
            z = depth[v, u]
            pc = np.stack([(u + 0.5 - cam.cx) / cam.fx * z, (v + 0.5 - cam.cy) / cam.fy * z, z], 1)
            pts = ((pc - cam.t) @ cam.R)[::7].astype(np.float32)
    scene = MemoryScene(cams, 1, 30.0, [0], pts, np.zeros(len(pts), np.int64), [cams[-1].name], frames)
    return _brightened(scene, 1, factor) if factor else scene


def test_measured_exposure_finds_the_brightened_camera():
    from atgs.train.exposure import measure_scene_exposure

    plain = measure_scene_exposure(_textured_rig(None))
    assert np.abs(np.log(plain)).max() < 0.01, plain  # rendered alike: no gain to find
    g = measure_scene_exposure(_textured_rig(1.2))
    slot = 1  # camera 1 is the second training camera (the last one is held out)
    others = np.delete(g, slot, 0)
    # 1.2, less what saturates at 255 and the pull of the bright camera on the per-point medians
    ratio = g[slot] / np.median(others, 0)
    assert ((ratio > 1.12) & (ratio < 1.22)).all(), g
    assert np.abs(others / np.median(others, 0) - 1).max() < 0.03, g


def test_auto_turns_the_exposure_on_only_where_cameras_differ(tmp_path):
    m, t = preset("tiny")
    t.camera_exposure, t.iterations, t.eval_every = "auto", 2, 0
    off = Trainer(_textured_rig(None), m, t, tmp_path / "a")
    on = Trainer(_textured_rig(1.2), m, t, tmp_path / "b")
    assert off.cfg.camera_exposure == "off" and off.exposure is None
    assert on.cfg.camera_exposure == "on" and on.exposure is not None
    # the learned gains start at the measured ones (already normalised to their geometric mean)
    assert np.allclose(on.exposure.gains_biases()[0].numpy(), on.measured_exposure, atol=1e-5)
    t.exposure_start_measured = False
    at_one = Trainer(_textured_rig(1.2), m, t, tmp_path / "c")
    assert torch.equal(at_one.exposure.table, torch.zeros_like(at_one.exposure.table))
    on.run_steps(progress=False)
    assert read_checkpoint(tmp_path / "b" / "ckpt.pt")["train_config"]["camera_exposure"] == "on"  # resolved


def test_evaluating_a_training_camera_applies_its_exposure(tmp_path):
    # No held-out camera: the trainer scores its first training camera, which it must render as
    # that camera was exposed, not at the cameras' average exposure.
    from atgs.eval.evaluate import EvalConfig, evaluate
    from atgs.eval.metrics import psnr as psnr_of

    scene = dataclasses.replace(make_toy_scene(num_frames=4, num_cameras=4, width=32, height=24, keyframes=2),
                                test_cameras=[])
    m, t = growing_tiny_config(3)
    t.camera_exposure = "on"
    tr = Trainer(scene, m, t, tmp_path)
    with torch.no_grad():  # camera 0 exposed 1.5x brighter and a little bluer than the others
        tr.exposure.table.zero_()
        tr.exposure.table[0, :3] = math.log(1.5)
        tr.exposure.table[0, 5] = 0.05
    ev = tr.evaluate(frames=[0, 2])
    plain = evaluate(tr.model, scene, EvalConfig(frames=(0, 2), cameras=("cam00",), lpips=False, progress=False,
                                                 images_per_camera=0), None, background=tr.cfg.background,
                     keep_renders=True)
    expected = []
    for f in (0, 2):
        render = torch.from_numpy(plain.renders[("cam00", f)])
        exposed = tr.exposure.apply(render, 0).detach().clamp(0, 1)
        expected.append(float(psnr_of(exposed, torch.from_numpy(scene.image(0, f)).float())))
    assert not ev["on_test_cameras"]
    assert ev["psnr"] == pytest.approx(sum(expected) / 2, abs=1e-4)
    assert abs(ev["psnr"] - plain.mean("psnr")) > 0.1  # the exposure changed what was scored
