"""Gaussian dropout (atgs.train.dropout): schedule, opacity compensation, trainer wiring."""

import pytest
import torch

from atgs.errors import UserError
from atgs.gaussians import Gaussians
from atgs.render import rasterize_gaussians
from atgs.train.dropout import drop_gaussians, drop_rate
from atgs.train.trainer import Trainer
from builders import growing_tiny_config, make_toy_scene, side_camera


def _gaussians(n: int, opacity: float = 0.4, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    return Gaussians(means=torch.rand(n, 3, generator=g), quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                     scales=torch.full((n, 3), 0.05), opacities=torch.full((n,), opacity),
                     colors=torch.rand(n, 3, generator=g))


def test_rate_rises_linearly_to_its_maximum():
    assert drop_rate(0.3, 0, 100) == 0.0
    assert drop_rate(0.3, 50, 100) == pytest.approx(0.15)
    assert drop_rate(0.3, 100, 100) == pytest.approx(0.3)
    assert drop_rate(0.3, 250, 100) == pytest.approx(0.3)  # a resumed run past its end stays capped
    assert drop_rate(0.0, 50, 100) == 0.0


def test_dropped_fraction_and_compensation():
    g = _gaussians(100_000, opacity=0.4)
    out = drop_gaussians(g, 0.3, torch.Generator().manual_seed(1))
    dropped = out.opacities == 0
    # binomial standard deviation of the fraction: sqrt(0.3 * 0.7 / 1e5) = 0.0014
    assert abs(dropped.float().mean().item() - 0.3) < 0.01
    assert torch.allclose(out.opacities[~dropped], torch.tensor(0.4 / 0.7))
    assert abs(out.opacities.mean().item() - 0.4) < 0.01  # expected opacity kept
    for name in ("means", "quats", "scales", "colors"):
        assert getattr(out, name) is getattr(g, name)
    assert drop_gaussians(g, 0.0, torch.Generator()) is g
    opaque = drop_gaussians(_gaussians(1000, opacity=0.9), 0.3, torch.Generator().manual_seed(1)).opacities
    assert opaque.max() == 1.0 and set(opaque.unique().tolist()) == {0.0, 1.0}  # capped: a valid opacity


def test_same_seed_drops_the_same_gaussians():
    g = _gaussians(1000)
    a = drop_gaussians(g, 0.2, torch.Generator().manual_seed(7)).opacities
    b = drop_gaussians(g, 0.2, torch.Generator().manual_seed(7)).opacities
    c = drop_gaussians(g, 0.2, torch.Generator().manual_seed(8)).opacities
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_expected_render_of_a_gaussian_is_the_undropped_render():
    # One Gaussian, alpha below the clamp: the image is linear in its opacity, so kept with
    # probability 1 - r at opacity o / (1 - r) and dropped otherwise averages to the render at o.
    cam, r = side_camera(), 0.3
    g = _gaussians(1, opacity=0.5)
    g.means[:] = torch.tensor([0.5, 0.5, 0.5])
    g.scales[:] = 0.2
    bg = torch.tensor([0.2, 0.3, 0.4])
    full = rasterize_gaussians(g, cam, background=bg).image
    kept = Gaussians(g.means, g.quats, g.scales, g.opacities / (1 - r), g.colors)
    empty = Gaussians(g.means, g.quats, g.scales, torch.zeros_like(g.opacities), g.colors)
    expected = (1 - r) * rasterize_gaussians(kept, cam, background=bg).image \
        + r * rasterize_gaussians(empty, cam, background=bg).image
    assert (full - bg).abs().max() > 0.1  # the Gaussian covers pixels
    assert torch.allclose(expected, full, atol=1e-5)


def test_a_rate_of_one_is_refused(tmp_path):
    scene = make_toy_scene(num_frames=4, num_cameras=4, width=32, height=24, keyframes=2)
    m, t = growing_tiny_config(5)
    t.drop_gaussians = 1.0
    with pytest.raises(UserError, match="drop-gaussians"):
        Trainer(scene, m, t, tmp_path)
    with pytest.raises(ValueError, match="below 1"):
        drop_gaussians(_gaussians(4), 1.0, torch.Generator())


def test_training_with_dropout_changes_the_run_and_resumes_exactly(tmp_path):
    scene = make_toy_scene(num_frames=6, num_cameras=5, width=40, height=32, keyframes=3)

    def config(rate):
        m, t = growing_tiny_config(10)
        t.drop_gaussians = rate
        return m, t

    plain = Trainer(scene, *config(0.0), tmp_path / "plain")
    plain.train(progress=False, final_renders=False)
    full = Trainer(scene, *config(0.5), tmp_path / "full")
    full.train(progress=False, final_renders=False)
    half = Trainer(scene, *config(0.5), tmp_path / "half")
    half.train(progress=False, stop_at=5)
    resumed = Trainer.resume(scene, tmp_path / "half" / "ckpt.pt", tmp_path / "half")
    resumed.train(progress=False, final_renders=False)
    a, b, c = ({**tr.model.sparse_tensors(), **tr.model.decoder.state_dict()} for tr in (plain, full, resumed))
    assert a.keys() == b.keys() == c.keys()
    assert any(a[k].shape != b[k].shape or not torch.equal(a[k], b[k]) for k in a)
    assert all(torch.equal(b[k], c[k]) for k in b)


def test_a_gaussian_with_an_identity_is_dropped_whichever_others_were_decoded():
    """The trainer draws per identity (anchor * q + slot): the same Gaussian meets the same draw
    in a decode of every anchor and in one that culled some (several workers' culling may differ
    from one process's by a few anchors). Reference: the full decode's decisions."""
    g = _gaussians(1000)
    ids = torch.randperm(5000, generator=torch.Generator().manual_seed(3))[:1000]
    full = drop_gaussians(g, 0.3, torch.Generator().manual_seed(9), ids, 5000).opacities
    subset = torch.arange(0, 1000, 3)
    sub = Gaussians(*(t[subset] for t in g.as_tuple()))
    part = drop_gaussians(sub, 0.3, torch.Generator().manual_seed(9), ids[subset], 5000).opacities
    assert torch.equal(part, full[subset])
    assert 0.2 < float((full == 0).float().mean()) < 0.4
    # in order (no identities), the same subset meets other draws
    assert not torch.equal(drop_gaussians(sub, 0.3, torch.Generator().manual_seed(9)).opacities, full[subset])
