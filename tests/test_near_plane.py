"""The model's near plane (atgs.model.near_plane): a fraction of the training cameras' distance
to the scene, fixed when the model is built, saved with it, and the one every render culls with."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from atgs.cameras import Camera
from atgs.config_checks import ConfigError
from atgs.geometry.reach import spheres_in_frustum
from atgs.model.atgs_model import ATGSModel
from atgs.model.near_plane import near_of, near_plane
from atgs.render.constants import NEAR
from atgs.timeline import evenly_spaced
from builders import ring_cameras, tiny_config


def _model(cameras, train_cameras=None, **overrides) -> ATGSModel:
    cfg = tiny_config(K=2, W=2, M=1, **overrides)
    pts = torch.rand(60, 3, generator=torch.Generator().manual_seed(0)) * 0.4 - 0.2
    kf = torch.arange(2).repeat_interleave(30)
    return ATGSModel.from_points(cfg, pts, kf, evenly_spaced(6, 2), 6, 10.0, cameras, train_cameras, seed=0)


def test_near_plane_is_a_fraction_of_the_median_camera_distance() -> None:
    cams = ring_cameras(3, radius=4.0, height=0.0) + ring_cameras(2, radius=10.0, height=0.0)
    assert near_plane(cams, np.zeros(3), 0.05) == pytest.approx(0.05 * 4.0)
    assert near_plane(cams, np.zeros(3), 0.0) == NEAR  # 0: the fixed near plane of before
    assert near_plane([], np.zeros(3), 0.05) == NEAR
    at_centre = Camera("c", 32, 24, np.array([[30, 0, 16], [0, 30, 12], [0, 0, 1.0]]), np.eye(4))
    assert near_plane([at_centre], np.zeros(3), 0.05) == NEAR  # no scale to measure


def test_the_model_near_plane_comes_from_training_cameras_only() -> None:
    train = ring_cameras(4, radius=4.0, height=0.0)
    close = ring_cameras(1, radius=0.5, height=0.0)[0]  # a held-out camera right at the content
    alone = _model(train)
    with_held_out = _model(train + [close], train)
    assert alone.near == with_held_out.near == pytest.approx(0.05 * 4.0, rel=0.05)
    assert _model(train, near_fraction=0.0).near == NEAR


def test_the_near_plane_round_trips_and_old_states_get_the_old_one() -> None:
    model = _model(ring_cameras(3, radius=4.0))
    state = model.state_dict()
    back = ATGSModel.from_state(model.cfg, state, 6, 10.0, model.cameras)
    assert back.near == model.near > NEAR
    old = {k: v for k, v in state.items() if k != "near"}  # a checkpoint from before the field
    assert ATGSModel.from_state(model.cfg, old, 6, 10.0, model.cameras).near == NEAR


def test_near_of_sources_without_one_is_the_default() -> None:
    assert near_of(object()) == NEAR
    model = _model(ring_cameras(3, radius=4.0))
    assert near_of(model) == model.near


@pytest.mark.parametrize("fraction", [-0.1, 1.0, float("nan")])
def test_a_bad_fraction_is_refused(fraction: float) -> None:
    with pytest.raises(ConfigError, match="--model.near-fraction"):
        tiny_config(near_fraction=fraction).validate()


def test_anchor_culling_uses_the_near_plane() -> None:
    """A point anchor between 0.01 and the model's near plane reaches no Gaussian it draws."""
    cam = ring_cameras(1, radius=4.0, height=0.0)[0]
    centres = torch.as_tensor(np.stack([cam.center + 0.1 * (-cam.center / 4.0), np.zeros(3)]), dtype=torch.float32)
    radii = torch.zeros(2)
    assert spheres_in_frustum(centres, radii, cam, 0.15).tolist() == [True, True]
    assert spheres_in_frustum(centres, radii, cam, 0.15, near=0.2).tolist() == [False, True]
    model = _model([cam])
    model.anchor_mu = centres
    model.reach.settled = model.reach.recent = torch.zeros(2)  # measured: point-sized anchors
    model.anchor_keyframe = torch.full((2,), -1)
    model.anchor_velocity = torch.zeros(2, 3)
    assert model.visible_anchors(0, [cam]).tolist() == [False, True]
