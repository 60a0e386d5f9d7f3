"""atgs-view --headless and atgs-render on a tiny real checkpoint; clear errors, exit code 2."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from atgs.headless_gl import HeadlessGLError
from atgs.render import rasterize_gaussians
from atgs.timeline import frame_at
from atgs.viewer.cli import main, render_main
from atgs.viewer.output import display_rgb, to_uint8
from atgs.viewer.scene_utils import cameras_path, orbit_path, resized
from builders import write_tiny_checkpoint


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tiny_checkpoint(tmp_path_factory.mktemp("viewer") / "ckpt.pt")


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 10 * math.log10(1.0 / max(mse, 1e-20))


def test_headless_frame_matches_rasterizer_of_the_model(ckpt: Path, tmp_path: Path) -> None:
    import atgs

    out = tmp_path / "frame.png"
    assert main([str(ckpt), "--headless", "--time", "0.5", "--camera", "2", "--out", str(out), "--gl", "osmesa"]) == 0
    img = np.asarray(Image.open(out), dtype=np.float64) / 255.0
    model = atgs.load(ckpt)
    cam = model.cameras[2]
    ref = rasterize_gaussians(model.gaussians_at(0.5), cam, backend="torch").image.numpy()
    assert img.shape == (cam.height, cam.width, 3)
    assert ref.std() > 0.02  # the tiny model draws something
    assert _psnr(img, ref) >= 35.0


def _reference_rgb8(model, frame: int, cam, mode: str = "color") -> np.ndarray:
    """What the viewer should show: the training rasterizer's image (torch reference) of the
    frame, or its depth/alpha through the display mapping of the mode, as uint8."""
    out = rasterize_gaussians(model.gaussians_at_frame(frame), cam, backend="torch")
    first = out.depth.numpy()[..., None].repeat(3, -1) if mode == "depth" else out.image.numpy()
    return to_uint8(display_rgb(np.concatenate([first, out.alpha.numpy()[..., None]], -1), mode, (0.0, 0.0, 0.0)))


def _psnr8(a: np.ndarray, b: np.ndarray) -> float:
    return _psnr(a / 255.0, b / 255.0)


@pytest.mark.parametrize("mode", ["depth", "alpha"])
def test_headless_modes_size_and_frame_match_the_rasterizer(ckpt: Path, tmp_path: Path, mode: str) -> None:
    import atgs

    out = tmp_path / f"{mode}.png"
    assert main([str(ckpt), "--headless", "--frame", "8", "--mode", mode, "--size", "48x36", "--out", str(out),
                 "--gl", "osmesa"]) == 0
    img = np.asarray(Image.open(out))
    model = atgs.load(ckpt)
    ref = _reference_rgb8(model, 8, resized(model.cameras[0], (48, 36)), mode)
    assert img.shape == (36, 48, 3) and ref.std() > 20  # covered and empty pixels both present
    assert _psnr8(img, ref) >= 45.0
    other = _reference_rgb8(model, 0, resized(model.cameras[1], (48, 36)), mode)
    assert _psnr8(img, other) < 30.0, "another frame and camera must not match"


def test_missing_and_corrupt_checkpoints_exit_2_with_one_line(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint at all")
    out = tmp_path / "keep.png"
    out.write_bytes(b"existing")
    for path in (tmp_path / "missing.pt", bad):
        assert main([str(path), "--headless", "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and str(path) in err and "Traceback" not in err
    assert out.read_bytes() == b"existing"  # failed runs never touch the output
    assert render_main([str(tmp_path / "missing.pt"), "--out", str(tmp_path / "v.mp4")]) == 2
    assert not (tmp_path / "v.mp4").exists()


def test_bad_arguments_exit_2(ckpt: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    for args, needle in (
        (["--camera", "7"], "--camera 7"),
        (["--time", "1.5"], "--time"),
        (["--size", "big"], "--size"),
        (["--frame", "99"], "--frame 99"),
        (["--min-alpha", "0"], "--min-alpha 0"),
        (["--min-alpha", "1.5"], "--min-alpha 1.5"),
    ):
        assert main([str(ckpt), "--headless", "--out", str(tmp_path / "x.png"), *args]) == 2
        err = capsys.readouterr().err
        assert needle in err and err.strip().count("\n") == 0


def test_unavailable_opengl_is_a_clear_error(ckpt: Path, tmp_path: Path, monkeypatch, capsys) -> None:
    import atgs.viewer.headless as vh

    def no_gl(backend: str = "auto"):
        raise HeadlessGLError("no headless OpenGL 3.3 available; install Mesa: apt-get install libegl-mesa0 libosmesa6")

    monkeypatch.setattr(vh, "create_headless_context", no_gl)
    assert main([str(ckpt), "--headless", "--out", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err
    assert "apt-get install" in err and "Traceback" not in err


def test_too_old_opengl_is_refused() -> None:
    from atgs.headless_gl import _check_version

    class OldContext:
        version_code = 210
        info = {"GL_VERSION": "2.1 Mesa"}
        released = False

        def release(self) -> None:
            self.released = True

    ctx = OldContext()
    with pytest.raises(HeadlessGLError, match="needs 3.3"):
        _check_version(ctx, "OSMesa")
    assert ctx.released


@pytest.mark.parametrize("path", ["orbit", "cameras"])
def test_render_video_matches_reference_frames(ckpt: Path, tmp_path: Path, path: str) -> None:
    """Every decoded video frame i is the rasterizer's image of sequence frame round(i (F-1) / (n-1))
    from path camera i (H.264 at crf 18 costs a little), and not that of another i."""
    import av

    import atgs

    out = tmp_path / f"{path}.mp4"
    assert render_main([str(ckpt), "--path", path, "--out", str(out), "--frames", "5", "--size", "64x48",
                        "--fps", "12", "--gl", "osmesa"]) == 0
    with av.open(str(out)) as c:
        frames = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
        rate = c.streams.video[0].average_rate
    assert len(frames) == 5 and frames[0].shape == (48, 64, 3)
    assert float(rate) == pytest.approx(12.0)
    model = atgs.load(ckpt)
    cams = (orbit_path if path == "orbit" else cameras_path)(model.cameras, 5)
    refs = [_reference_rgb8(model, frame_at(i / 4, model.num_frames), resized(c, (64, 48))) for i, c in enumerate(cams)]
    for i, f in enumerate(frames):
        scores = [_psnr8(f, r) for r in refs]
        assert scores[i] >= 35.0 and max(s for j, s in enumerate(scores) if j != i) < 30.0, (i, scores)


def test_cameras_path_passes_through_training_cameras() -> None:
    from builders import ring_cameras

    cams = ring_cameras(3, (96, 72), focal=80.0)
    path = cameras_path(cams, 5)  # 2 segments: samples 0, 2, 4 are the cameras
    for i, c in zip((0, 2, 4), cams):
        np.testing.assert_allclose(path[i].w2c, c.w2c, atol=1e-9)
    # midpoint rotation is orthonormal and between its neighbours
    R = path[1].R
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    orbit = orbit_path(cams, 8)
    radii = [np.linalg.norm(c.center[:2]) for c in orbit]
    np.testing.assert_allclose(radii, 3.0, atol=1e-6)  # the rig's radius around its look center
    for c in orbit:  # every orbit camera looks at the center (origin)
        uv, z = c.project(np.zeros((1, 3)))
        np.testing.assert_allclose(uv[0], [c.cx, c.cy], atol=1e-6)


def test_depth_video_uses_one_colormap_range(ckpt: Path, tmp_path: Path, monkeypatch) -> None:
    import atgs.viewer.output as vo

    ranges: list = []
    real = vo.display_rgb

    def spy(raw, mode, background, zrange=None):
        ranges.append(zrange)
        return real(raw, mode, background, zrange)

    monkeypatch.setattr("atgs.viewer.headless.display_rgb", spy)
    out = tmp_path / "depth.mp4"
    assert render_main([str(ckpt), "--mode", "depth", "--out", str(out), "--frames", "3", "--size", "32x24",
                        "--gl", "osmesa"]) == 0
    assert len(ranges) == 3 and ranges[0] is not None and all(r == ranges[0] for r in ranges)


def test_device_option(ckpt: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    # --device cpu and auto render the same frame (auto is the CPU here unless CUDA is present)
    imgs = []
    for device in ("cpu", "auto"):
        out = tmp_path / f"{device}.png"
        assert main([str(ckpt), "--headless", "--frame", "3", "--out", str(out), "--gl", "osmesa", "--device", device]) == 0
        imgs.append(np.asarray(Image.open(out), dtype=np.float64) / 255.0)
    assert _psnr(imgs[0], imgs[1]) >= 45.0  # identical on the CPU; CUDA rounds the rotations alike
    if not torch.cuda.is_available():  # asking for CUDA without one: one line, exit 2, no output
        out = tmp_path / "cuda.png"
        assert main([str(ckpt), "--headless", "--out", str(out), "--device", "cuda"]) == 2
        err = capsys.readouterr().err.strip()
        assert "--device cuda" in err and "--device cpu" in err and err.count("\n") == 0
        assert not out.exists()


def test_default_background_is_the_trained_one(tmp_path: Path) -> None:
    """Without --background, atgs-view draws over the checkpoint's training background (what
    atgs-eval renders over); --background overrides it."""
    import atgs
    from atgs.checkpoint import read_checkpoint, save_checkpoint

    data = read_checkpoint(write_tiny_checkpoint(tmp_path / "plain.pt"))
    data["train_config"] = {"background": [0.2, 0.5, 0.8]}
    ckpt = tmp_path / "ckpt.pt"
    save_checkpoint(ckpt, data)
    model = atgs.load(ckpt)
    assert model.background == (0.2, 0.5, 0.8)
    cam = resized(model.cameras[0], (48, 36))
    alpha = rasterize_gaussians(model.gaussians_at_frame(0), cam, backend="torch").alpha.numpy()
    empty = alpha < 1e-3
    assert empty.any() and (~empty).any()
    for extra, want in (([], (0.2, 0.5, 0.8)), (["--background", "0", "0", "0"], (0.0, 0.0, 0.0))):
        out = tmp_path / f"bg{len(extra)}.png"
        assert main([str(ckpt), "--headless", "--frame", "0", "--size", "48x36", "--out", str(out), "--gl", "osmesa",
                     *extra]) == 0
        img = np.asarray(Image.open(out), dtype=np.float64) / 255.0
        assert np.abs(img[empty] - np.asarray(want)).max() < 2.0 / 255, extra


def test_covered_arc_is_the_circle_minus_the_largest_gap() -> None:
    from atgs.viewer.scene_utils import covered_arc

    start, span = covered_arc(np.radians([350.0, 10.0, 30.0]))  # wraps through 0
    assert math.degrees(start) == pytest.approx(350.0) and math.degrees(span) == pytest.approx(40.0)
    start, span = covered_arc(np.radians([0.0, 90.0, 180.0, 270.0]))
    assert math.degrees(span) == pytest.approx(270.0)
    assert covered_arc(np.array([1.0])) == (1.0, 0.0)


def _azimuths(cams) -> np.ndarray:
    return np.degrees(np.arctan2([c.center[1] for c in cams], [c.center[0] for c in cams]))


def test_orbit_of_a_front_facing_rig_stays_over_the_captured_arc() -> None:
    """Five cameras on a 60-degree arc around the origin: the orbit sweeps that arc to both ends
    and back (it starts at the middle) instead of a revolution that looks at the uncaptured
    back; a ring of twelve still gets one revolution in equal steps."""
    from atgs.cameras import Camera, look_at

    K = np.array([[80.0, 0, 48], [0, 80.0, 36], [0, 0, 1]])
    arc = np.radians(np.linspace(60.0, 120.0, 5))
    cams = [Camera(f"c{i}", 96, 72, K, look_at(np.array([3 * np.cos(a), 3 * np.sin(a), 1.0]), np.zeros(3),
                                                np.array([0, 0, 1.0]))) for i, a in enumerate(arc)]
    orbit = orbit_path(cams, 40)
    az = _azimuths(orbit)
    assert az.min() == pytest.approx(60.0, abs=0.5) and az.max() == pytest.approx(120.0, abs=0.5)
    assert az[0] == pytest.approx(90.0, abs=1e-6)
    for c in orbit:
        uv, _ = c.project(np.zeros((1, 3)))
        np.testing.assert_allclose(uv[0], [c.cx, c.cy], atol=1e-6)

    from builders import ring_cameras

    steps = np.diff(np.unwrap(np.radians(_azimuths(orbit_path(ring_cameras(12, (96, 72)), 24)))))
    np.testing.assert_allclose(np.degrees(steps), 15.0, atol=1e-6)


def test_orbit_of_one_camera_is_a_revolution_and_of_a_close_pair_a_30_degree_sweep() -> None:
    from builders import ring_cameras

    one = ring_cameras(1, (96, 72), height=0.0)  # level: its up is the scene's z
    steps = np.diff(np.unwrap(np.radians(_azimuths(orbit_path(one, 8, np.zeros(3))))))
    np.testing.assert_allclose(np.degrees(steps), 45.0, atol=1e-6)
    pair = [ring_cameras(360, (96, 72), height=0.0)[k] for k in (0, 4)]  # 4 degrees apart
    az = _azimuths(orbit_path(pair, 40, np.zeros(3)))
    assert az.max() - az.min() == pytest.approx(30.0, abs=0.2) and az[0] == pytest.approx(2.0, abs=1e-6)


def test_shared_flags_mean_the_same_in_both_commands() -> None:
    """The flags atgs-view and atgs-render share are spelled and parsed alike (one dataclass),
    and each command keeps its own defaults for the flags it does not share."""
    import tyro

    from atgs.viewer.cli import RenderConfig, ViewConfig, render_settings

    args = ["run/ckpt.pt", "--gl", "osmesa", "--mode", "depth", "--scale-modifier", "0.5",
            "--background", "0.1", "0.2", "0.3", "--min-alpha", "0.02", "--device", "cpu"]
    view, render = tyro.cli(ViewConfig, args=args), tyro.cli(RenderConfig, args=args)
    for cfg in (view, render):
        assert (cfg.checkpoint, cfg.gl, cfg.device) == ("run/ckpt.pt", "osmesa", "cpu")
        s = render_settings(cfg)
        assert (s.mode, s.scale_modifier, s.background, s.min_alpha) == ("depth", 0.5, (0.1, 0.2, 0.3), 0.02)
    assert (view.out, render.out) == (Path("frame.png"), Path("video.mp4"))
    with pytest.raises(SystemExit):
        tyro.cli(RenderConfig, args=["ckpt.pt", "--mode", "normals"])


def test_decode_gl_option(ckpt: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """--decode gl (decode and sort in compute shaders) renders what --decode torch renders, in
    atgs-view --headless and atgs-render; what it cannot decode is one line and exit 2."""
    import av

    imgs = []
    for route in ("torch", "gl"):
        out = tmp_path / f"{route}.png"
        assert main([str(ckpt), "--headless", "--frame", "5", "--out", str(out), "--decode", route]) == 0
        imgs.append(np.asarray(Image.open(out), dtype=np.float64) / 255.0)
    assert imgs[0].std() > 0.01 and _psnr(imgs[0], imgs[1]) >= 45.0
    videos = []
    for route in ("torch", "gl"):
        out = tmp_path / f"{route}.mp4"
        assert render_main([str(ckpt), "--path", "orbit", "--out", str(out), "--frames", "4", "--size", "64x48",
                            "--decode", route]) == 0
        with av.open(str(out)) as c:
            videos.append([f.to_ndarray(format="rgb24") for f in c.decode(video=0)])
    assert len(videos[1]) == 4
    for a, b in zip(*videos):
        assert _psnr8(a, b) >= 40.0
    out = tmp_path / "demo.png"
    capsys.readouterr()  # (the renders' progress bars)
    assert main(["demo", "--headless", "--out", str(out), "--decode", "gl"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--decode gl" in err and "--decode torch" in err and err.count("\n") == 0 and not out.exists()
