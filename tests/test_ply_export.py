"""atgs-export: a trained checkpoint -> per-frame 3DGS PLY files + manifest.json, and the round
trip: the player opening the folder draws what it draws from the checkpoint itself."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

import atgs
from atgs.cli.export import main
from atgs.export import ExportError, parse_frames
from atgs.io.gaussian_ply import read_gaussian_ply
from atgs.viewer.cli import main as view_main
from atgs.viewer.loading import load_source
from atgs.viewer.scene_utils import resized
from atgs.viewer.source import decode_frame
from atgs.viewer.splat_renderer import RenderSettings
from builders import train_tiny_checkpoint


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return train_tiny_checkpoint(tmp_path_factory.mktemp("export") / "run")


@pytest.fixture(scope="module")
def exported(ckpt: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("exported") / "plys"
    assert main([str(ckpt), "--out", str(out), "--frames", "0:6:2", "--no-progress"]) == 0
    return out


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return 10 * math.log10(1.0 / max(mse, 1e-20))


def test_frames_spec() -> None:
    assert parse_frames(None, 5) == [0, 1, 2, 3, 4]
    assert parse_frames("0:120:2", 7) == [0, 2, 4, 6]  # stop beyond the end: Python's slice rule
    assert parse_frames("1:", 4) == [1, 2, 3] and parse_frames("::3", 7) == [0, 3, 6] and parse_frames("-2:", 5) == [3, 4]
    assert parse_frames("4,0,2,2", 5) == [0, 2, 4]
    for bad, needle in (("1:2:3:4", "expected"), ("a:b", "expected"), ("1,x", "expected"), ("0,9", "frame 9 out of range"),
                        ("3:1", "selects no frame"), ("0:4:0", "expected")):
        with pytest.raises(ExportError, match=needle):
            parse_frames(bad, 5)


def test_export_writes_frames_and_manifest(ckpt: Path, exported: Path) -> None:
    model = atgs.load(ckpt)
    assert sorted(p.name for p in exported.iterdir()) == [
        "frame_000000.ply", "frame_000002.ply", "frame_000004.ply", "manifest.json"]
    man = json.loads((exported / "manifest.json").read_text())
    assert man["format"] == "atgs-ply-sequence" and man["version"] == 1 and man["sh_degree"] == 0
    assert man["fps"] == model.fps and man["num_frames"] == model.num_frames == 6
    assert man["frames"] == [0, 2, 4] and man["files"] == ["frame_000000.ply", "frame_000002.ply", "frame_000004.ply"]
    assert man["cameras"] == [c.to_dict() for c in model.cameras] and man["test_cameras"] == model.test_camera_names
    assert man["source"] == {"checkpoint": str(ckpt.resolve()), "step": 30}
    assert man["near"] == model.near > 0.01  # the model's near plane: what ATGS's players cull with
    assert load_source(exported).near == model.near
    for f, name, count in zip(man["frames"], man["files"], man["gaussians"]):
        g = model.gaussians_at_frame(f)
        back = read_gaussian_ply(exported / name)
        assert count == len(g) == len(back.gaussians) and back.sh_degree == 0
        torch.testing.assert_close(back.gaussians.means, g.means, rtol=0, atol=0)
        torch.testing.assert_close(back.gaussians.colors, g.colors, rtol=0, atol=2e-7)  # through rgb_to_sh0
        torch.testing.assert_close(back.gaussians.opacities, g.opacities, rtol=1e-6, atol=0)
    assert exported.stat().st_mode & 0o077, "a published folder has the umask's permissions, not mkdtemp's 0700"


def test_the_player_draws_the_exported_frames_like_the_checkpoint(ckpt: Path, exported: Path, renderer) -> None:
    """Round trip: the folder played headless equals the checkpoint played headless, for every
    exported frame and every training camera (colours as SH degree 0 drawn by the shader's SH
    path against the checkpoint's 16-bit colours)."""
    model, plys = atgs.load(ckpt), load_source(exported)
    assert plys.num_frames == 3 and plys.fps == model.fps / 2  # every 2nd frame: real time is kept
    assert [c.to_dict() for c in plys.cameras] == [c.to_dict() for c in model.cameras]
    settings = RenderSettings(exact_sort=True, background=(0.1, 0.2, 0.3))
    worst = math.inf
    for i, f in enumerate(plys.sequence.numbers):
        packed = decode_frame(plys, i)
        assert packed.sh_degree == 0
        for cam in model.cameras:
            cam = resized(cam, (96, 72))
            renderer.set_gaussians(decode_frame(model, f))
            ref = renderer.render_image(cam, settings)
            renderer.set_gaussians(packed)
            img = renderer.render_image(cam, settings)
            assert np.abs(ref - np.float32(settings.background)).max() > 0.1  # the model draws something
            worst = min(worst, _psnr(img, ref))
    print(f"round trip: worst PSNR {worst:.1f} dB over {plys.num_frames} frames x {len(model.cameras)} cameras")
    assert worst >= 50.0, f"PLY vs checkpoint: {worst:.1f} dB"
    other = renderer.render_image(resized(model.cameras[0], (96, 72)), settings)
    assert _psnr(other, img) < 35.0, "another camera must not match"


def test_headless_command_on_the_folder_matches_the_checkpoint(ckpt: Path, exported: Path, tmp_path: Path) -> None:
    a, b = tmp_path / "ply.png", tmp_path / "ckpt.png"
    assert view_main([str(exported), "--headless", "--frame", "2", "--camera", "3", "--gl", "osmesa",
                      "--size", "96x72", "--out", str(a)]) == 0  # the 3rd file: sequence frame 4
    assert view_main([str(ckpt), "--headless", "--frame", "4", "--camera", "3", "--gl", "osmesa",
                      "--size", "96x72", "--out", str(b)]) == 0
    ia, ib = (np.asarray(Image.open(p), dtype=np.float64) / 255 for p in (a, b))
    assert ib.std() > 0.02 and _psnr(ia, ib) >= 50.0


def test_min_opacity_drops_faint_gaussians(ckpt: Path, tmp_path: Path) -> None:
    model = atgs.load(ckpt)
    g = model.gaussians_at_frame(1)
    cut = float(g.opacities.median())
    out = tmp_path / "thin"
    assert main([str(ckpt), "--out", str(out), "--frames", "1", "--min-opacity", str(cut), "--no-progress"]) == 0
    back = read_gaussian_ply(out / "frame_000001.ply").gaussians
    keep = g.opacities >= cut
    assert 0 < len(back) == int(keep.sum()) < len(g)
    torch.testing.assert_close(back.means, g.means[keep], rtol=0, atol=0)
    assert json.loads((out / "manifest.json").read_text())["min_opacity"] == cut


def test_existing_output_is_refused_or_replaced_whole(ckpt: Path, tmp_path: Path, capsys, monkeypatch) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    assert main([str(ckpt), "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("atgs-export: error: ") and "--overwrite" in err and "\n" not in err
    assert [p.name for p in out.iterdir()] == ["keep.txt"]

    import atgs.export as export

    calls = []

    def failing_write(path, g, sh=None):  # the disk fills up at the third frame
        calls.append(path)
        if len(calls) == 3:
            raise OSError(28, "No space left on device")
        return real_write(path, g, sh)

    real_write = export.write_gaussian_ply
    monkeypatch.setattr(export, "write_gaussian_ply", failing_write)
    assert main([str(ckpt), "--out", str(out), "--overwrite", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert "No space left on device" in err and "nothing was written" in err and "\n" not in err, err
    assert [p.name for p in out.iterdir()] == ["keep.txt"] and sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    calls.clear()

    def interrupted_write(path, g, sh=None):  # Ctrl-C at the second frame
        calls.append(path)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real_write(path, g, sh)

    monkeypatch.setattr(export, "write_gaussian_ply", interrupted_write)
    assert main([str(ckpt), "--out", str(out), "--overwrite", "--no-progress"]) == 130
    assert capsys.readouterr().err.strip().splitlines()[-1] == "atgs-export: interrupted"
    assert [p.name for p in out.iterdir()] == ["keep.txt"] and sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    monkeypatch.undo()
    assert main([str(ckpt), "--out", str(out), "--overwrite", "--no-progress"]) == 0
    assert len(list(out.glob("frame_*.ply"))) == 6 and not (out / "keep.txt").exists()


def test_bad_arguments_exit_2(ckpt: Path, tmp_path: Path, capsys) -> None:
    for args, needle in (([str(tmp_path / "missing.pt")], "checkpoint not found"),
                         ([str(ckpt), "--frames", "7"], "frame 7 out of range"),
                         ([str(ckpt), "--min-opacity", "1.5"], "--min-opacity 1.5")):
        assert main([*args, "--out", str(tmp_path / "o"), "--no-progress"]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("atgs-export: error: ") and needle in err and "\n" not in err, err
    assert not (tmp_path / "o").exists()
