"""No Gaussian inside a training camera's own housing (atgs.geometry.clearance): the ball test
against a per-point loop, the radius rule on a ring, both decodes cutting the same Gaussians, a
held-out camera's pose used for nothing (its housing, which the training cameras see, stays in
front of its lens), and checkpoints."""

import numpy as np
import torch

from builders import randomize_features, ring_cameras, tiny_config
from atgs.geometry.clearance import CameraClearance, clearance_radius
from atgs.model.atgs_model import ATGSModel
from atgs.render import rasterize_gaussians


def test_outside_matches_a_loop_over_points_and_cameras():
    cams = ring_cameras(20, radius=3.0)
    gen = torch.Generator().manual_seed(0)
    centres = torch.tensor(np.stack([c.center for c in cams]), dtype=torch.float32)
    # points near the cameras (a third inside a 0.3 ball) and elsewhere
    near = centres[torch.randint(0, 20, (3000,), generator=gen)] + 0.2 * torch.randn(3000, 3, generator=gen)
    pts = torch.cat([near, torch.rand(2000, 3, generator=gen) * 8 - 4])
    got = CameraClearance.of_cameras(cams, 0.3).outside(pts).numpy()
    want = np.array([all(np.linalg.norm(p - c.center) >= 0.3 for c in cams) for p in pts.double().numpy()])
    assert 500 < (~want).sum() < 4500
    assert np.array_equal(got, want)
    assert CameraClearance.of_cameras(cams, 0.0).outside(pts).all()  # radius 0: off


def test_radius_is_the_fraction_of_the_camera_to_scene_distance():
    cams = ring_cameras(10, radius=6.5, height=0.0)
    assert abs(clearance_radius(cams, np.zeros(3), 0.02) - 0.13) < 1e-9
    assert clearance_radius(cams, np.zeros(3), 0.0) == 0.0


def _held_out_body_model(clearance: float, held_out: bool = False):
    """A 6-camera ring of radius 3 whose scene is a cloud at the centre, plus anchors on cam00's
    housing, 0.03 in front of its lens (as the cameras opposite reconstruct it); every Gaussian
    sits at its anchor and is nearly opaque. ``held_out``: cam00 is held out (the others train)."""
    cams = ring_cameras(6, size=(40, 30), radius=3.0, height=0.0)
    cfg = tiny_config(K=1, W=0, M=1, hidden=8, anchor_layout="per-keyframe", voxel_size=0.02,
                      camera_clearance=clearance)
    gen = torch.Generator().manual_seed(0)
    c0 = torch.tensor(cams[0].center, dtype=torch.float32)
    body = c0 * (1 - 0.03 / 3.0) + 0.008 * torch.randn(200, 3, generator=gen)
    scene = torch.rand(300, 3, generator=gen) * 1.2 - 0.6
    pts = torch.cat([body, scene])
    model = ATGSModel.from_points(cfg, pts, torch.zeros(len(pts), dtype=torch.int64), [0], 1, 10.0, cams,
                                  train_cameras=cams[1:] if held_out else None, seed=0)
    randomize_features(model, gen, grid_scale=0.1)
    with torch.no_grad():  # offsets near zero: each anchor's Gaussians sit at it
        model.decoder.offset[2].weight.mul_(0.0)
        model.decoder.offset[2].bias.zero_()
        model.decoder.opacity[2].bias.fill_(4.0)
    return model, cams


@torch.no_grad()
def test_both_decodes_drop_the_gaussians_in_a_cameras_housing():
    model, cams = _held_out_body_model(0.02)  # radius 0.06: the housing, not the scene
    assert abs(model.clearance.radius - 0.06) < 0.01
    fast = model.gaussians_at_frame(0)
    ref = model.gaussians_at_frame_reference(0)
    assert torch.allclose(fast.means, ref.means, atol=1e-5) and fast.means.shape == ref.means.shape
    open_model, _ = _held_out_body_model(0.0)
    everything = open_model.gaussians_at_frame_reference(0)
    c0 = torch.tensor(cams[0].center, dtype=torch.float32)
    inside = (everything.means - c0).norm(dim=1) < model.clearance.radius
    assert inside.sum() >= 20  # the housing's Gaussians are there without the clearance ...
    assert len(ref.means) == len(everything.means) - int(inside.sum())  # ... and only they go
    assert ((ref.means - c0).norm(dim=1) >= model.clearance.radius).all()


@torch.no_grad()
def test_a_training_camera_sees_the_scene_not_its_own_housing():
    """cam00 as a training camera: without the clearance its housing, just in front of its lens,
    covers its image; with it, cam00 sees what the scene alone gives."""
    bg = torch.tensor([0.2, 0.3, 0.4])
    model, cams = _held_out_body_model(0.02)
    open_model, _ = _held_out_body_model(0.0)
    c0 = torch.tensor(cams[0].center, dtype=torch.float32)
    everything = open_model.gaussians_at_frame(0)
    keep = (everything.means - c0).norm(dim=1) >= model.clearance.radius
    scene_only = everything.map(lambda t: t[keep])
    want = rasterize_gaussians(scene_only, cams[0], background=bg).image
    blocked = rasterize_gaussians(everything, cams[0], background=bg).image
    got = rasterize_gaussians(model.gaussians_at_frame(0), cams[0], background=bg).image
    assert (blocked - want).abs().mean() > 0.05  # the housing covers the view without the clearance
    assert torch.allclose(got, want, atol=1e-5)


@torch.no_grad()
def test_a_held_out_camera_gets_no_clearance_its_housing_stays():
    """cam00 held out: its pose is used for nothing, so no ball clears its housing, which the
    training cameras see, and which covers cam00's own image (what a held-out score on such a
    rig honestly pays); the radius comes from the training cameras alone."""
    bg = torch.tensor([0.2, 0.3, 0.4])
    model, cams = _held_out_body_model(0.02, held_out=True)
    assert model.test_camera_names == ["cam00"]
    assert abs(model.clearance.radius - 0.06) < 0.01
    got = np.stack([c.center for c in cams[1:]])
    assert np.allclose(model.clearance.centres.numpy(), got, atol=1e-6)  # the training cameras only
    open_model, _ = _held_out_body_model(0.0, held_out=True)
    everything = open_model.gaussians_at_frame(0)
    for g in (model.gaussians_at_frame(0), model.gaussians_at_frame_reference(0)):
        assert torch.equal(g.means, everything.means)  # nothing is near a training camera: nothing goes
    c0 = torch.tensor(cams[0].center, dtype=torch.float32)
    keep = (everything.means - c0).norm(dim=1) >= model.clearance.radius
    scene_only = rasterize_gaussians(everything.map(lambda t: t[keep]), cams[0], background=bg).image
    seen = rasterize_gaussians(model.gaussians_at_frame(0), cams[0], background=bg).image
    assert (seen - scene_only).abs().mean() > 0.05


def test_the_clearance_follows_the_held_out_cameras():
    """A model's balls are its cameras less ``test_camera_names``, however it was built (a loaded
    checkpoint learns its held-out cameras after it is built)."""
    model, cams = _held_out_body_model(0.02)
    assert model.clearance.centres.shape[0] == 6
    model.test_camera_names = ["cam00", "cam03"]
    want = np.stack([c.center for c in cams if c.name not in ("cam00", "cam03")])
    assert np.allclose(model.clearance.centres.numpy(), want, atol=1e-6)
    model.test_camera_names = []
    assert model.clearance.centres.shape[0] == 6


def test_checkpoints_keep_the_radius_and_older_ones_load_without_one():
    model, cams = _held_out_body_model(0.02)
    state = model.state_dict()
    back = ATGSModel.from_state(model.cfg, state, 1, 10.0, cams)
    assert back.clearance.radius == model.clearance.radius > 0
    back.test_camera_names = ["cam00"]  # (as atgs.checkpoint sets them from the checkpoint)
    assert back.clearance.centres.shape[0] == 5 and back.clearance.radius == model.clearance.radius
    old = {k: v for k, v in state.items() if k != "camera_clearance"}
    assert ATGSModel.from_state(model.cfg, old, 1, 10.0, cams).clearance.radius == 0.0
