"""The web player in a real browser (Debian's Chromium, software WebGL2) against the desktop player.

The built-in scene's generator at a small size, trained a few steps, is exported with
``atgs-export --format web``; the page opens it, seeks and its canvas is read back and compared
with ``atgs-view --headless`` of the same checkpoint, camera and frame (the renderer atgs-render
uses). Broken streams must show an error on the page, not a blank canvas."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import torch
import pytest

from atgs.eval.metrics import psnr
from atgs.web.browser import PlayerPage, chromium, serving

# What the page draws against atgs-view here (Debian's Chromium 156 with SwiftShader, this
# module's checkpoint; measured 2026-11-29 by printing the PSNR of the test below, run with -s):
# the Gaussian chunks 57.5 dB (frame 5) and 58.0 dB (frame 10); the model stream at int8, decoded
# by the page and drawn from its floats, 60.7 and 60.4 dB (58.2 and 57.9 dB when the page still
# quantized the decoded Gaussians into a chunk frame; on the built-in scene's larger model:
# bench/results/web.json "bytes"). Each kind's mark is a few dB under what it draws, so that
# a change to the projection's or the decode's numerics fails it, while SwiftShader's and a GPU's
# rounding do not. (Issue 39's target was 35 dB.)
PSNR_MIN_DB = {"gaussians": 54.0, "model": 54.0}


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(psnr(torch.from_numpy(a).double(), torch.from_numpy(b).double()))


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    """The built-in scene's generator (4 cameras, 96x72, 12 frames) trained 40 steps of ``tiny``."""
    from atgs.data.scene import PreparedScene
    from atgs.data.synth.scene import SynthConfig
    from atgs.data.synth.videos import ensure_default_scene
    from atgs.train.config import preset
    from atgs.train.trainer import Trainer

    root = tmp_path_factory.mktemp("web")
    cfg = SynthConfig(frames=12, cameras=4, width=96, height=72, texture_size=128)
    scene = PreparedScene.load(ensure_default_scene(root / "cache", cfg, keyframes=2, progress=False))
    m, t = preset("tiny")
    t.iterations = 40
    Trainer(scene, m, t, root / "run").train(progress=False, final_renders=False)
    return root / "run" / "ckpt.pt"


def _export(checkpoint: Path, out: Path, *args: str) -> Path:
    from atgs.cli.export import main as export_main

    assert export_main([str(checkpoint), "--out", str(out), "--format", "web", "--no-progress", *args]) == 0
    return out


@pytest.fixture(scope="module")
def export(checkpoint, tmp_path_factory) -> Path:
    """The Gaussian chunk stream (4 frames a chunk)."""
    return _export(checkpoint, tmp_path_factory.mktemp("export") / "web", "--web-stream", "gaussians",
                   "--chunk-frames", "4")


@pytest.fixture(scope="module")
def model_export(checkpoint, tmp_path_factory) -> Path:
    """The default export: the model stream (the page decodes the model on its GPU), int8."""
    return _export(checkpoint, tmp_path_factory.mktemp("export") / "web")


@pytest.fixture(scope="module")
def browser():
    with chromium() as b:
        yield b


def _desktop_frame(checkpoint: Path, camera: int, frame: int, out: Path) -> np.ndarray:
    from atgs.io.images import read_rgb8
    from atgs.viewer.cli import main as view_main

    assert view_main([str(checkpoint), "--headless", "--gl", "osmesa", "--device", "cpu", "--camera", str(camera),
                      "--frame", str(frame), "--out", str(out)]) == 0
    return read_rgb8(out).astype(np.float32) / 255.0


@pytest.mark.parametrize("kind", ["gaussians", "model"])
def test_the_browser_draws_what_atgs_render_draws(kind, checkpoint, request, browser, tmp_path):
    folder = request.getfixturevalue("export" if kind == "gaussians" else "model_export")
    with serving(folder) as url:
        page = PlayerPage(browser, url, {"camera": 1, "paused": 1, "size": "camera"})
        page.first_frame()
        for frame in (5, 10):  # two seeks, across chunks (4 frames each) and keyframe windows
            page.seek(frame)
            got = page.pixels()
            want = _desktop_frame(checkpoint, 1, frame, tmp_path / f"f{frame}.png")
            assert got.shape == want.shape
            psnr = _psnr(got, want)
            print(f"page against atgs-view: {kind} frame {frame}: {psnr:.2f} dB")
            assert psnr >= PSNR_MIN_DB[kind], (frame, psnr, page.console)
            assert float(got.std()) > 0.02  # a picture, not a flat colour
        state = page.state()
        assert state["error"] in (None, "") and state["frames"] == 12
        # either kind holds its files in the window's part of the budget (stream.js / model_stream.js memory())
        assert 0 < state["heldBytes"] <= state["windowBudgetBytes"] < state["budgetBytes"]
        page.close()


def _broken_copy(export: Path, tmp_path: Path) -> Path:
    out = tmp_path / "broken"
    shutil.copytree(export, out)
    return out


def test_a_truncated_chunk_is_an_error_on_the_page(export, browser, tmp_path):
    broken = _broken_copy(export, tmp_path)
    chunk = broken / "stream" / "chunk_000001.bin"
    chunk.write_bytes(chunk.read_bytes()[: chunk.stat().st_size // 2])
    with serving(broken) as url:
        page = PlayerPage(browser, url, {"paused": 1})
        page.first_frame()  # chunk 0 is whole: the first frame still shows
        page.page.evaluate("() => { window.atgsPlayer.seek(5); }")  # chunk 1 never arrives whole
        text = page.error_text()
        assert "chunk_000001.bin" in text and "truncated" in text
        page.close()


def test_a_missing_chunk_is_an_error_on_the_page(export, browser, tmp_path):
    broken = _broken_copy(export, tmp_path)
    (broken / "stream" / "chunk_000000.bin").unlink()
    with serving(broken) as url:
        page = PlayerPage(browser, url, {})
        text = page.error_text()
        assert "chunk_000000.bin" in text and "missing" in text
        assert page.state()["framesDrawn"] == 0
        page.close()


def test_a_missing_manifest_is_an_error_on_the_page(export, browser, tmp_path):
    broken = _broken_copy(export, tmp_path)
    (broken / "stream" / "manifest.json").unlink()
    with serving(broken) as url:
        page = PlayerPage(browser, url, {})
        assert "manifest.json" in page.error_text()
        page.close()
