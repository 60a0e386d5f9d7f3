"""The real player window under Xvfb: opens a checkpoint (or its PLY export), plays, scrubs, screenshots."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from builders import write_tiny_checkpoint


@pytest.mark.parametrize("opened", ["checkpoint", "ply folder", "checkpoint decoded on the GL"])
def test_window_plays_scrubs_and_screenshots(tmp_path: Path, opened: str) -> None:
    """The same session on a checkpoint, on its atgs-export folder (24 PLY files + manifest), and
    on the checkpoint with frames decoded and sorted in compute shaders (``--decode gl``)."""
    if shutil.which("xvfb-run") is None:
        pytest.fail("xvfb-run is missing: apt-get install xvfb xauth")
    source = ckpt = write_tiny_checkpoint(tmp_path / "ckpt.pt", num_frames=24)
    if opened == "ply folder":
        import atgs
        from atgs.export import export_ply_sequence

        source = export_ply_sequence(atgs.load(ckpt), tmp_path / "plys", list(range(24)), progress=False).out
    shot = tmp_path / "shot.png"
    cmd = [
        "xvfb-run", "-a", "-s", "-screen 0 640x480x24",
        sys.executable, str(Path(__file__).with_name("viewer_driver.py")), str(source), str(shot),
        "--camera", "1", "--size", "320x240", "--frames", "12",
        "--decode", "gl" if opened.endswith("on the GL") else "torch",
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stderr[-2000:]
    report = json.loads(shot.with_suffix(".json").read_text())
    assert report["window_size"] == [320, 240]
    assert "llvmpipe" in report["gl"] or "Mesa" in report["gl"]
    assert report["distinct_played"] >= 2, report["played_frames"]  # playback advanced
    played, playhead = report["played_frames"], report["playhead_frames"]
    assert len(played) + 1 == len(playhead)
    for i, f in enumerate(played):  # never a frame the playhead has not reached (no jumping ahead)
        assert f in playhead[: i + 2], (i, played, playhead)
    assert report["scrub_shown"] == report["scrub_target"] == round(0.75 * 23)
    assert report["gaussians"] > 0 and 0 < report["drawn"] <= report["gaussians"]
    inputs = report["inputs"]  # keyboard and mouse went through imgui's input queue
    assert inputs["right_arrow_step"] == 1 and inputs["left_arrow_back"]
    assert inputs["space_plays"] and inputs["space_pauses"]
    assert inputs["key2_mode"] == "depth" and inputs["key3_mode"] == "alpha"
    assert inputs["speed_after_equal"] == 2.0
    assert inputs["camera_after_c"] == 2  # opened on camera 1, C snaps to the next one
    assert inputs["reset_restores_home"] and inputs["fly_mode"]
    assert inputs["w_moves_forward"] > 0
    assert inputs["ui_hidden"] and inputs["ui_shown_again"]
    assert inputs["drag_orbit_moved_eye"] > 1e-3 and inputs["drag_orbit_kept_pivot"] < 1e-6
    assert 0.5 < inputs["wheel_zoom_ratio"] < 1.0
    window = np.asarray(Image.open(shot))
    assert window.shape == (240, 320, 3) and window.std() > 5.0  # UI + splats, not a blank window
    splats = np.asarray(Image.open(report["splats_screenshot"]), dtype=np.float64)
    assert (splats.max(axis=2) > 10).mean() > 0.02  # the splats cover part of the view


def test_window_without_display_is_a_clear_error(tmp_path: Path) -> None:
    import os

    ckpt = write_tiny_checkpoint(tmp_path / "ckpt.pt")
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    proc = subprocess.run([sys.executable, "-m", "atgs.viewer.cli", str(ckpt)], capture_output=True, text=True,
                          timeout=120, env=env)
    assert proc.returncode == 2
    err = proc.stderr.strip()
    assert err.count("\n") == 0 and "xvfb-run" in err and "Traceback" not in err, err
