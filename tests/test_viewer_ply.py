"""atgs-view / atgs-render opening 3DGS PLY files: a degree-3 file written here byte by byte (not
by the exporter) against the training rasterizer fed atgs.sh colours for each camera; folders of
per-frame files; bad input as one line and exit code 2."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from atgs.cameras import Camera, look_at
from atgs.gaussians import Gaussians
from atgs.io.gaussian_ply import GaussianPlyError, write_gaussian_ply
from atgs.render import rasterize
from atgs.sh import sh_colors
from atgs.viewer.cli import main, render_main
from atgs.viewer.decode_cache import DecodeCache
from atgs.viewer.loading import load_source
from atgs.viewer.scene_utils import default_camera, resized
from atgs.viewer.source import decode_frame
from atgs.viewer.splat_renderer import RenderSettings

C1_SIGN_CHECK = 0.4886025119029199  # sqrt(3 / (4 pi)), the band-1 constant


def write_3dgs_ply_by_hand(path: Path, means: np.ndarray, quats: np.ndarray, log_scales: np.ndarray,
                           opacity_logits: np.ndarray, coeffs: np.ndarray) -> Path:
    """A binary little-endian PLY in the layout of the 3DGS reference code, written from the
    format's description alone: x y z nx ny nz f_dc_0..2 f_rest_0..3(K-1)-1 (all red
    coefficients 1..K-1, then green, then blue) opacity scale_0..2 rot_0..3, plus a property
    3DGS does not have (viewers must ignore it)."""
    n, K, _ = coeffs.shape
    rest = [f"f_rest_{i}" for i in range(3 * (K - 1))]
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", *rest, "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3", "extra_confidence"]
    rows = np.zeros(n, dtype=[(name, "<f4") for name in names])
    for i, axis in enumerate("xyz"):
        rows[axis] = means[:, i]
    for c in range(3):
        rows[f"f_dc_{c}"] = coeffs[:, 0, c]
        for k in range(1, K):
            rows[f"f_rest_{c * (K - 1) + k - 1}"] = coeffs[:, k, c]
    rows["opacity"] = opacity_logits
    for i in range(3):
        rows[f"scale_{i}"] = log_scales[:, i]
    for i in range(4):
        rows[f"rot_{i}"] = quats[:, i]
    rows["extra_confidence"] = 123.0
    header = "ply\nformat binary_little_endian 1.0\ncomment written by hand\nelement vertex %d\n" % n
    header += "".join(f"property float {name}\n" for name in names) + "end_header\n"
    path.write_bytes(header.encode("ascii") + rows.tobytes())
    return path


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return 10 * math.log10(1.0 / max(mse, 1e-20))


@pytest.fixture(scope="module")
def sh3_scene(tmp_path_factory: pytest.TempPathFactory):
    """400 random Gaussians with strongly view-dependent degree-3 colour, in a hand-written file."""
    rng = np.random.default_rng(7)
    n = 400
    means = rng.uniform([-1, -0.75, -1], [1, 0.75, 1], (n, 3)).astype(np.float32)
    quats = rng.normal(size=(n, 4)).astype(np.float32)  # not normalized: readers normalize
    log_scales = rng.uniform(-4.0, -2.5, (n, 3)).astype(np.float32)
    logits = rng.uniform(-2.0, 3.0, n).astype(np.float32)
    coeffs = (rng.normal(size=(n, 16, 3)) * 0.6).astype(np.float32)
    coeffs[:, 0] = rng.uniform(-1.5, 1.5, (n, 3))
    path = write_3dgs_ply_by_hand(tmp_path_factory.mktemp("sh3") / "scene.ply", means, quats, log_scales, logits,
                                  coeffs)
    return path, means, quats, log_scales, logits, coeffs


def _reference(scene, cam: Camera, bg=(0.0, 0.0, 0.0)) -> np.ndarray:
    """The training rasterizer fed the same Gaussians, coloured by atgs.sh for this camera."""
    _, means, quats, log_scales, logits, coeffs = scene
    m = torch.from_numpy(means)
    colors = sh_colors(3, torch.from_numpy(coeffs).double(), m.double(), torch.from_numpy(cam.center)).float()
    return rasterize(m, torch.from_numpy(quats), torch.exp(torch.from_numpy(log_scales)),
                     torch.sigmoid(torch.from_numpy(logits)), colors, torch.from_numpy(cam.w2c).float(),
                     torch.from_numpy(cam.K).float(), cam.width, cam.height, background=torch.tensor(bg),
                     backend="torch").image.numpy()


def test_sh3_ply_headless_matches_the_rasterizer(sh3_scene, tmp_path: Path) -> None:
    path, means = sh3_scene[0], sh3_scene[1]
    out = tmp_path / "frame.png"
    assert main([str(path), "--headless", "--size", "96x72", "--gl", "osmesa", "--out", str(out)]) == 0
    img = np.asarray(Image.open(out), dtype=np.float64) / 255.0
    cam = resized(default_camera(means), (96, 72))  # a file without cameras opens on the framing camera
    ref = np.clip(_reference(sh3_scene, cam), 0, 1)
    assert ref.std() > 0.05 and _psnr(img, ref) >= 35.0, _psnr(img, ref)


def test_sh3_colour_follows_the_camera(sh3_scene, renderer) -> None:
    source = load_source(sh3_scene[0])
    assert source.num_frames == 1 and source.cameras == [] and source.sequence.sh_degree == 3
    packed = decode_frame(source, 0)
    assert packed.sh_degree == 3
    renderer.set_gaussians(packed)
    bg = (0.2, 0.1, 0.3)
    K = np.array([[80.0, 0, 47.3], [0, 82.0, 35.6], [0, 0, 1]])
    cams = [Camera(f"c{i}", 96, 72, K, look_at(np.array(eye), np.zeros(3), np.array([0.0, -1.0, 0.0])))
            for i, eye in enumerate(([0.9, -0.7, -2.6], [-2.4, -0.5, 1.0], [1.5, 1.2, 2.0]))]
    for cam in cams:
        img = renderer.render_image(cam, RenderSettings(background=bg, exact_sort=True))
        p = _psnr(img, _reference(sh3_scene, cam, bg))
        assert p >= 35.0, f"{cam.name}: {p:.1f} dB"
    # colours evaluated for another viewpoint do not match: the shader really uses the view direction
    _, means, quats, log_scales, logits, coeffs = sh3_scene
    wrong = sh_colors(3, torch.from_numpy(coeffs), torch.from_numpy(means), torch.from_numpy(cams[0].center).float())
    cam = cams[2]
    mixed = rasterize(torch.from_numpy(means), torch.from_numpy(quats), torch.exp(torch.from_numpy(log_scales)),
                      torch.sigmoid(torch.from_numpy(logits)), wrong, torch.from_numpy(cam.w2c).float(),
                      torch.from_numpy(cam.K).float(), 96, 72, background=torch.tensor(bg), backend="torch").image
    assert _psnr(img, mixed.numpy()) < 30.0


def _numbered_folder(root: Path, names: list[str]) -> list[Gaussians]:
    """Files whose one Gaussian sits at x = the number in the name."""
    root.mkdir()
    out = []
    for name in names:
        x = float(name.split("_")[-1].split(".")[0])
        g = Gaussians(torch.tensor([[x, 0.0, 0.0]]), torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.1),
                      torch.tensor([0.9]), torch.tensor([[1.0, 0.0, 0.0]]))
        write_gaussian_ply(root / name, g)
        out.append(g)
    return out


def test_folder_plays_in_the_order_of_the_numbers_in_the_names(tmp_path: Path) -> None:
    folder = tmp_path / "seq"
    _numbered_folder(folder, ["shot_10.ply", "shot_2.ply", "shot_1.ply"])
    (folder / "notes.txt").write_text("not a frame")
    source = load_source(folder)
    assert source.num_frames == 3 and source.fps == 30.0 and source.cameras == []
    assert [float(source.gaussians_at_frame(i).means[0, 0]) for i in range(3)] == [1.0, 2.0, 10.0]
    assert float(source.gaussians_at(1.0).means[0, 0]) == 10.0
    assert load_source(folder, fps=12.5).fps == 12.5
    # the player's decode thread reads the files (Gaussians, then SH, of the same frame)
    with DecodeCache(lambda f: decode_frame(source, f), capacity=4) as cache:
        cache.request([2, 0, 1])
        got = {f: cache.wait_for(f) for f in (2, 0, 1)}
    assert [float(got[f].means[0, 0]) for f in range(3)] == [1.0, 2.0, 10.0]
    assert all(p.sh_degree == 0 for p in got.values())


def test_render_orbits_a_file_without_cameras_around_its_gaussians(sh3_scene, tmp_path: Path) -> None:
    out = tmp_path / "orbit"
    assert render_main([str(sh3_scene[0]), "--out", str(out), "--frames", "6", "--size", "48x36",
                        "--gl", "osmesa"]) == 0
    frames = sorted(out.glob("*.png"))
    assert len(frames) == 6
    for f in frames:  # the scene stays in view all the way round
        img = np.asarray(Image.open(f), dtype=np.float64)
        assert (img.max(axis=2) > 10).mean() > 0.2, f.name


def test_render_a_folder_with_its_manifest(tmp_path: Path) -> None:
    from atgs.io.atomic import write_json_atomic
    from atgs.io.ply_sequence import sequence_manifest

    folder = tmp_path / "seq"
    _numbered_folder(folder, ["frame_000000.ply", "frame_000003.ply", "frame_000006.ply"])
    cams = [Camera("a", 40, 30, np.array([[40.0, 0, 20], [0, 40, 15], [0, 0, 1]]),
                   look_at(np.array([3.0, -6.0, 1.0]), np.array([3.0, 0, 0])))]
    write_json_atomic(folder / "manifest.json", sequence_manifest(24.0, 7, [0, 3, 6], [], [], cams, [], 0.0, {}))
    source = load_source(folder)
    assert source.fps == 8.0 and [c.name for c in source.cameras] == ["a"]  # every 3rd frame of 24 fps
    out = tmp_path / "video"
    assert render_main([str(folder), "--out", str(out), "--path", "cameras", "--gl", "osmesa"]) == 0
    imgs = [np.asarray(Image.open(p), dtype=np.float64) for p in sorted(out.glob("*.png"))]
    assert len(imgs) == 3 and imgs[0].shape == (30, 40, 3)
    xs = [np.nonzero(img[..., 0].max(0) > 50)[0].mean() for img in imgs]  # the blob moves right: x = 0, 3, 6
    assert xs[0] < xs[1] < xs[2]


def test_the_near_plane_of_a_folder_is_its_manifests(tmp_path: Path) -> None:
    """An export's manifest carries the model's near plane; older manifests and folders without one
    play with the default 0.01; a bad one is a one-line error."""
    import json

    from atgs.io.ply_sequence import sequence_manifest
    from atgs.viewer.ply_source import PlySource

    folder = tmp_path / "seq"
    _numbered_folder(folder, ["frame_000000.ply", "frame_000001.ply"])
    assert PlySource.open(folder).near == 0.01  # no manifest
    man = sequence_manifest(24.0, 2, [0, 1], [], [], [], [], 0.0, {}, near=0.25)
    (folder / "manifest.json").write_text(json.dumps(man))
    assert PlySource.open(folder).near == 0.25
    del man["near"]  # written before the near plane was
    (folder / "manifest.json").write_text(json.dumps(man))
    assert PlySource.open(folder).near == 0.01
    (folder / "manifest.json").write_text(json.dumps({**man, "near": -1}))
    with pytest.raises(GaussianPlyError, match="'near' must be a number > 0"):
        PlySource.open(folder)


# --- bad input --------------------------------------------------------------------------------------

@pytest.fixture()
def bad_inputs(tmp_path: Path) -> dict[str, tuple[Path, str]]:
    """name -> (path to open, what the one-line message must say)."""
    good = tmp_path / "good.ply"
    write_gaussian_ply(good, Gaussians(torch.zeros(4, 3), torch.ones(4, 4), torch.ones(4, 3), torch.full((4,), 0.5),
                                       torch.ones(4, 3)))
    truncated = tmp_path / "truncated.ply"
    truncated.write_bytes(good.read_bytes()[:-7])
    raw = good.read_bytes()
    no_opacity = tmp_path / "no_opacity.ply"  # a 4-byte property renamed: still a valid PLY, but not 3DGS
    no_opacity.write_bytes(raw.replace(b"property float opacity", b"property float opaque_"))
    empty = tmp_path / "empty"
    empty.mkdir()
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    g = Gaussians(torch.zeros(2, 3), torch.ones(2, 4), torch.ones(2, 3), torch.full((2,), 0.5), torch.ones(2, 3))
    write_gaussian_ply(mixed / "f_0.ply", g)
    write_gaussian_ply(mixed / "f_1.ply", g, torch.zeros(2, 4, 3))  # SH degree 1 in the second file
    return {"truncated": (truncated, "truncated or corrupt"), "no opacity": (no_opacity, "'opacity' is missing"),
            "empty folder": (empty, "no .ply files"), "mixed folder": (mixed / "f_1.ply", "same properties")}


def test_bad_input_is_one_line_and_exit_code_2(bad_inputs, tmp_path: Path, capsys) -> None:
    out = tmp_path / "keep.png"
    out.write_bytes(b"existing")
    for name, (path, needle) in bad_inputs.items():
        target = path.parent if name == "mixed folder" else path
        for prog, run in (("atgs-view", lambda t: main([str(t), "--headless", "--out", str(out)])),
                          ("atgs-render", lambda t: render_main([str(t), "--out", str(tmp_path / "v.mp4")]))):
            assert run(target) == 2, (prog, name)
            err = capsys.readouterr().err.strip()
            assert err.startswith(f"{prog}: error: ") and "\n" not in err and "Traceback" not in err, err
            assert needle in err and str(path) in err, (name, err)
    assert out.read_bytes() == b"existing" and not (tmp_path / "v.mp4").exists()


def test_bad_input_in_a_real_process(bad_inputs, tmp_path: Path) -> None:
    path = bad_inputs["truncated"][0]
    proc = subprocess.run([sys.executable, "-m", "atgs.viewer.cli", str(path), "--headless", "--out",
                           str(tmp_path / "x.png")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and proc.stdout == ""
    err = proc.stderr.strip()
    assert err.count("\n") == 0 and err.startswith("atgs-view: error: ") and str(path) in err, err


def test_a_run_folder_points_to_its_checkpoint(tmp_path: Path, capsys) -> None:
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "ckpt.pt").write_bytes(b"x")
    assert main([str(tmp_path / "run"), "--headless", "--out", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert "a training run" in err and str(tmp_path / "run" / "ckpt.pt") in err and "\n" not in err
