"""Training's culled decode shows every camera what evaluation's full decode shows it
(atgs.geometry.reach): checked against the full decode's render, on rigs whose cameras see each
other, and the sphere-frustum test against points sampled on the spheres."""

import numpy as np
import pytest
import torch

from builders import randomize_features, ring_cameras, tiny_config, random_point_model
from atgs.cameras import Camera, look_at
from atgs.geometry.reach import spheres_in_frustum
from atgs.render import rasterize_gaussians
from atgs.render.constants import NEAR


def _inside(cam: Camera, pts: np.ndarray, margin: float) -> np.ndarray:
    uv, z = cam.project(pts)
    mw, mh = margin * cam.width, margin * cam.height
    with np.errstate(invalid="ignore", divide="ignore"):
        return (z > NEAR) & (uv[:, 0] > -mw) & (uv[:, 0] < cam.width + mw) & (uv[:, 1] > -mh) & (uv[:, 1] < cam.height + mh)


def test_sphere_test_is_the_centre_test_at_radius_zero_and_never_drops_a_reaching_sphere():
    cam = ring_cameras(1, (40, 30), radius=3.0)[0]
    gen = torch.Generator().manual_seed(0)
    centres = torch.rand(3000, 3, generator=gen) * 8 - 4
    radii = torch.rand(3000, generator=gen) * 1.5
    got0 = spheres_in_frustum(centres, torch.zeros(3000), cam, 0.15).numpy()
    assert np.array_equal(got0, _inside(cam, centres.double().numpy(), 0.15))
    got = spheres_in_frustum(centres, radii, cam, 0.15).numpy()
    # points on and in each sphere: any that falls inside the frustum makes its sphere visible
    dirs = torch.randn(64, 3, generator=gen)
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    for s in (0.5, 1.0):
        pts = centres[:, None, :] + s * radii[:, None, None] * dirs[None]
        hit = _inside(cam, pts.reshape(-1, 3).double().numpy(), 0.15).reshape(3000, 64).any(1)
        assert not (hit & ~got).any()
    assert got.sum() < 3000 and got.sum() > got0.sum()  # it still culls, and more spheres than centres pass


def _facing_pair() -> list[Camera]:
    """Two cameras 4 units apart looking at each other (each sees the other's body)."""
    K = np.array([[36.0, 0, 20], [0, 36.0, 15], [0, 0, 1]])
    a, b = np.array([-2.0, 0, 0]), np.array([2.0, 0, 0])
    up = np.array([0.0, 0, 1])
    return [Camera("cam00", 40, 30, K, look_at(a, b, up)), Camera("cam01", 40, 30, K, look_at(b, a, up))]


def _body_model(cams: list[Camera]):
    """Anchors on a 'camera body' just behind cam00 (as the other camera reconstructs it), whose
    Gaussians the decoder places in front of cam00's lens."""
    cfg = tiny_config(K=1, W=0, M=1, hidden=8, anchor_layout="per-keyframe", voxel_size=0.05)
    gen = torch.Generator().manual_seed(0)
    body = torch.tensor([-2.08, 0.0, 0.0]) + 0.04 * torch.randn(40, 3, generator=gen)
    scene = torch.rand(200, 3, generator=gen) * 1.6 - 0.8
    pts = torch.cat([body, scene])
    from atgs.model.atgs_model import ATGSModel

    model = ATGSModel.from_points(cfg, pts, torch.zeros(len(pts), dtype=torch.int64), [0], 1, 10.0, cams, seed=0)
    randomize_features(model, gen, grid_scale=0.1)
    with torch.no_grad():  # offsets of +0.3 units along x (towards cam01, in front of cam00)
        last = model.decoder.offset[2]
        last.weight.mul_(0.01)
        on_body = model.anchor_mu[:, 0] < -1.9
        unit = torch.exp(model.anchor_log_scale[on_body, :3]).mean(0)
        last.bias.copy_((torch.tensor([0.3, 0.0, 0.0]) / unit).repeat(cfg.gaussians_per_anchor))
    return model


@torch.no_grad()
def _render_pair(model, cam: Camera, f: int):
    culled = model.decode_frame(f, cam, track=False).gaussians  # first: a full decode measures every reach
    full = model.gaussians_at_frame_reference(f)
    bg = torch.tensor([0.2, 0.3, 0.4])
    return (rasterize_gaussians(full, cam, background=bg).image,
            rasterize_gaussians(culled, cam, background=bg).image)


def test_gaussians_of_anchors_behind_a_camera_reach_its_training_view():
    cams = _facing_pair()
    model = _body_model(cams)
    model.refresh_reach()
    full, culled = _render_pair(model, cams[0], 0)
    assert float((full - culled).abs().max()) < 1e-5
    # the centre alone (reach 0, the old test) drops the body's anchors: cam00's training view
    # would never show it the Gaussians in front of its lens, which evaluation draws
    model.reach.settled.zero_()
    model.reach.recent.fill_(-1.0)
    full, culled = _render_pair(model, cams[0], 0)
    assert float((full - culled).abs().max()) > 0.1


@pytest.mark.parametrize("velocity", [False, True])
def test_culled_training_views_equal_the_full_decode_on_a_ring_that_sees_itself(velocity):
    cams = ring_cameras(8, (40, 30), radius=1.2, height=0.2)  # inside the points: cameras see each other
    cfg = tiny_config(K=3, W=3, M=2, hidden=8, temporal_fade=velocity, anchor_velocity=velocity)
    model = random_point_model(cfg, 9, 600, cams, randomize=True)
    if velocity:
        model.anchor_velocity = 0.2 * torch.randn(model.anchor_velocity.shape, generator=torch.Generator().manual_seed(1))
    model.refresh_reach()
    views = [(cam, f) for cam in cams for f in (0, 4, 8)]
    bg = torch.tensor([0.2, 0.3, 0.4])
    with torch.no_grad():  # every culled decode before any full one: the refresh's reach alone
        decs = [model.decode_frame(f, cam, track=False) for cam, f in views]
        culled_any = any(len(d.active) < int(model.active_anchors(f).sum()) for d, (_, f) in zip(decs, views))
        for d, (cam, f) in zip(decs, views):
            full = rasterize_gaussians(model.gaussians_at_frame_reference(f), cam, background=bg).image
            culled = rasterize_gaussians(d.gaussians, cam, background=bg).image
            assert float((full - culled).abs().max()) < 1e-5, (cam.name, f)
    assert culled_any  # the cull is not vacuous


def test_reach_follows_anchor_edits_and_unknown_reach_is_never_culled():
    cams = ring_cameras(4, (40, 30))
    model = random_point_model(tiny_config(), 9, 200, cams, randomize=True)
    assert torch.isinf(model.reach.bound()).all()  # nothing measured: nothing culled
    assert model.refresh_reach() == model.num_anchors
    assert torch.isfinite(model.reach.bound()).all()
    assert model.refresh_reach() == model.num_anchors  # settled: all stale again
    n = model.num_anchors
    model.add_anchors(torch.zeros(2, 3), torch.zeros(2, model.cfg.feature_dim), torch.zeros(2, 6),
                      torch.zeros(2, dtype=torch.int64))
    assert torch.isinf(model.reach.bound()[n:]).all() and torch.isfinite(model.reach.bound()[:n]).all()
    keep = torch.ones(n + 2, dtype=torch.bool)
    keep[0] = False
    model.keep_anchors(keep)
    assert model.reach.bound().shape == (n + 1,)
