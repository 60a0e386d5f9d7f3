"""The background by direction (atgs.render.environment, atgs.train.background): the map's
lookup against an analytic map, its estimate from images of a known sky, compositing in the
rasterizer, the trainer's checkpoint, and the viewer's GLSL pass against the rasterizer."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from atgs.cameras import Camera, look_at
from atgs.render import rasterize, rasterize_gaussians
from atgs.render.environment import EnvironmentMap, pixel_directions
from atgs.render.validate import RasterInputError
from atgs.train.background import resolve_background
from builders import make_toy_scene, textured_copy

K = np.array([[60.0, 0, 40.0], [0, 60.0, 30.0], [0, 0, 1]])


def _camera(yaw_deg: float, pitch_deg: float = 0.0, name: str = "c", eye=(0.0, 0.0, 0.0)) -> Camera:
    y, p = math.radians(yaw_deg), math.radians(pitch_deg)
    eye = np.asarray(eye, dtype=np.float64)
    target = eye + np.array([math.cos(y) * math.cos(p), math.sin(y) * math.cos(p), math.sin(p)])
    return Camera(name, 80, 60, K, look_at(eye, target))


def _sky(d: np.ndarray) -> np.ndarray:
    """A smooth colour per world direction: what the test images show."""
    return 0.5 + 0.35 * np.stack([d[..., 0], d[..., 1], d[..., 2]], axis=-1)


class _SkyScene:
    """Cameras at the origin whose images show :func:`_sky` (one frame)."""

    def __init__(self, cameras: list[Camera]) -> None:
        self.cameras, self.num_frames = cameras, 1

    def image_uint8(self, c: int, f: int) -> np.ndarray:
        return np.round(255 * _sky(pixel_directions(self.cameras[c]))).astype(np.uint8)


def test_pixel_directions_project_back_to_their_pixels() -> None:
    cam = _camera(30, 10, eye=(1.0, -2.0, 0.5))
    d = pixel_directions(cam)
    uv, z = cam.project(cam.center + 3.0 * d.reshape(-1, 3))
    v, u = np.mgrid[0 : cam.height, 0 : cam.width]
    assert np.allclose(uv, np.stack([u + 0.5, v + 0.5], -1).reshape(-1, 2), atol=1e-6)
    assert (z > 0).all() and np.allclose(np.linalg.norm(d, axis=-1), 1.0)


def test_lookup_of_a_linear_map_is_exact() -> None:
    """Bilinear lookup reproduces a map linear in (azimuth, elevation) away from the seam."""
    h, w = 16, 32
    ys, xs = np.mgrid[0:h, 0:w]
    texels = np.stack([(xs + 0.5) / w, (ys + 0.5) / h, np.full((h, w), 0.25)], -1)
    env = EnvironmentMap(torch.tensor(texels), np.eye(3))
    rng = np.random.default_rng(0)
    az = rng.uniform(-math.pi + 0.2, math.pi - 0.2, 200)
    el = rng.uniform(-math.pi / 2 + 0.1, math.pi / 2 - 0.1, 200)
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
    got = env.lookup(d).numpy()
    assert np.allclose(got[:, 0], (az + math.pi) / (2 * math.pi), atol=1e-5)
    assert np.allclose(got[:, 1], (el + math.pi / 2) / math.pi, atol=1e-5)
    assert np.allclose(got[:, 2], 0.25)
    # around the seam the azimuth wraps: halfway between the last and the first column
    seam = env.lookup(np.array([[-1.0, 0.0, 0.0]])).numpy()[0, 0]
    assert seam == pytest.approx(0.5 * ((w - 0.5) / w + 0.5 / w), abs=1e-5)


def test_map_from_images_recovers_the_sky_between_the_cameras() -> None:
    """Eight cameras around the horizon (and a tilted world up): a held-out camera between two
    of them gets the sky's colour in each pixel's direction; one looking where no camera looked
    gets colours the cameras saw, not noise."""
    train = [_camera(45 * k, 5.0 * (k % 2), name=f"c{k}") for k in range(8)]
    held = _camera(22.5, 3.0, name="held")
    scene = _SkyScene(train + [held])
    colour, env = resolve_background(scene, list(range(8)))
    assert env is not None
    img = env.image(held).numpy()
    truth = _sky(pixel_directions(held))
    err = np.abs(img - truth)
    mean_colour = np.mean([scene.image_uint8(i, 0).reshape(-1, 3).mean(0) / 255 for i in range(8)], axis=0)
    assert np.allclose(colour, mean_colour, atol=0.01)  # the single colour stays the images' mean
    # the map's 12-degree blur leaves an error (largest at the edge of what the cameras saw, where
    # the average is one-sided) far below that of the best single colour
    assert err.mean() < 0.02 and err.max() < 0.08, (err.mean(), err.max())
    assert err.mean() < 0.2 * np.abs(truth - truth.reshape(-1, 3).mean(0)).mean()
    up = env.image(_camera(0, 89.0)).numpy()  # straight up: none of the cameras looked there
    seen = np.concatenate([scene.image_uint8(i, 0).reshape(-1, 3) / 255 for i in range(8)])
    assert np.isfinite(up).all()
    assert (up >= seen.min(0) - 0.02).all() and (up <= seen.max(0) + 0.02).all()


def test_uniform_backdrop_gets_no_map() -> None:
    class Black(_SkyScene):
        def image_uint8(self, c: int, f: int) -> np.ndarray:
            img = np.zeros((60, 80, 3), np.uint8)
            img[20:40, 30:50] = 200  # an object over black
            return img

    colour, env = resolve_background(Black([_camera(45 * k) for k in range(4)]), [0, 1, 2, 3])
    assert env is None and max(colour) < 0.01


def _gaussians(n: int = 300, seed: int = 0):
    from atgs.gaussians import Gaussians

    gen = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=gen) * torch.tensor([2.0, 4.0, 3.0]) - torch.tensor([1.0, 2.0, 1.5])
    means[:, 0] += 4.0  # in front of a camera at the origin looking along +x
    return Gaussians(means=means, quats=torch.randn(n, 4, generator=gen),
                     scales=torch.exp(torch.rand(n, 3, generator=gen) * 1.5 - 3.2),
                     opacities=torch.rand(n, generator=gen) * 0.8 + 0.1, colors=torch.rand(n, 3, generator=gen))


def test_per_pixel_background_composites_like_a_colour_and_its_gradient_is_transmittance() -> None:
    g, cam = _gaussians(), _camera(0)
    c = torch.tensor([0.2, 0.6, 0.4], dtype=torch.float64)
    args = [t.double() for t in g.as_tuple()] + [cam.w2c, cam.K, cam.width, cam.height]
    by_colour = rasterize(*args, background=c, backend="torch")  # the backend's own compositing
    image_bg = c.expand(cam.height, cam.width, 3).clone().requires_grad_(True)
    by_image = rasterize(*args, background=image_bg, backend="torch")
    assert float(by_colour.alpha.mean()) > 0.1 and float(by_colour.alpha.min()) < 0.5
    assert torch.allclose(by_image.image, by_colour.image, atol=1e-10)
    by_image.image.sum().backward()  # d image / d background = T = 1 - alpha, per channel
    assert torch.allclose(image_bg.grad, (1 - by_colour.alpha.detach())[..., None].expand(-1, -1, 3), atol=1e-10)
    with pytest.raises(RasterInputError, match="background"):
        rasterize(*args, background=torch.zeros(cam.height + 1, cam.width, 3, dtype=torch.float64), backend="torch")


def test_rasterize_gaussians_takes_an_environment_map() -> None:
    g, cam = _gaussians(seed=1), _camera(10, 5)
    texels = torch.rand(8, 16, 3, generator=torch.Generator().manual_seed(2))
    env = EnvironmentMap(texels, np.eye(3))
    out = rasterize_gaussians(g, cam, background=env, backend="torch")
    black = rasterize_gaussians(g, cam, backend="torch")
    expected = black.image + (1 - black.alpha)[..., None] * env.lookup(pixel_directions(cam))
    assert torch.allclose(out.image, expected, atol=1e-6)
    flat = EnvironmentMap(torch.full((8, 16, 3), 0.3), np.eye(3))  # a constant map is that colour
    assert torch.allclose(rasterize_gaussians(g, cam, background=flat, backend="torch").image,
                          rasterize_gaussians(g, cam, background=torch.full((3,), 0.3), backend="torch").image,
                          atol=1e-6)


def test_trainer_saves_and_evaluation_uses_the_map(tmp_path) -> None:
    import atgs
    from atgs.checkpoint import CheckpointError, read_checkpoint, save_checkpoint
    from atgs.eval.evaluate import EvalConfig, evaluate
    from atgs.train.config import preset
    from atgs.train.trainer import Trainer

    textured = textured_copy(make_toy_scene(num_frames=4, num_cameras=5, width=40, height=32, keyframes=2))
    m, t = preset("tiny")
    t.iterations, t.eval_every, t.eval_max_frames = 3, 0, 1
    tr = Trainer(textured, m, t, tmp_path / "run")
    assert tr.model.environment is not None
    tr.train(progress=False, final_renders=False)
    ckpt = tmp_path / "run" / "ckpt.pt"
    loaded = atgs.load(ckpt)
    assert torch.equal(loaded.environment.texels, tr.model.environment.texels)
    cfg = EvalConfig(frames=(0,), images_per_camera=0, lpips=False, progress=False)
    mine = evaluate(tr.model, textured, cfg, None)
    theirs = evaluate(loaded, textured, cfg, None)
    over_colour = evaluate(loaded, textured, cfg, None, background=loaded.background)
    assert mine.mean("psnr") == pytest.approx(theirs.mean("psnr"), abs=1e-6)
    assert mine.mean("psnr") != pytest.approx(over_colour.mean("psnr"), abs=1e-6)  # the map is what was used

    t.background_by_direction = False
    assert Trainer(textured, m, t, tmp_path / "off").model.environment is None

    data = read_checkpoint(ckpt)
    data["environment"] = {"texels": torch.zeros(4, 3)}  # not (H, W, 3), no basis
    save_checkpoint(tmp_path / "bad.pt", data)
    with pytest.raises(CheckpointError, match="environment map"):
        atgs.load(tmp_path / "bad.pt")


def test_viewer_draws_the_map_like_the_rasterizer(renderer) -> None:
    from atgs.viewer.packing import pack_gaussians
    from atgs.viewer.splat_renderer import RenderSettings

    g, cam = _gaussians(seed=3), _camera(-20, 15)
    ys, xs = np.mgrid[0:32, 0:64]
    texels = np.stack([0.5 + 0.4 * np.sin(xs / 64 * 2 * np.pi), ys / 31, 0.5 + 0.4 * np.cos(xs / 64 * 4 * np.pi)], -1)
    basis = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # a map frame not the world's
    env = EnvironmentMap(torch.tensor(texels), basis)
    ref = rasterize_gaussians(g, cam, background=env, backend="torch").image.numpy()
    renderer.set_gaussians(pack_gaussians(g))
    got = renderer.render_image(cam, RenderSettings(environment=env))
    mse = float(np.mean((got - ref) ** 2))
    assert 10 * math.log10(1 / mse) >= 35.0
    bare = renderer.render_image(cam, RenderSettings(background=(0.0, 0.0, 0.0)))
    assert float(np.abs(got - bare).mean()) > 0.05  # the map shows
