"""The camera path as a user makes it: in the real player window under Xvfb, three keyframes
added with the K key, a preview (V), Ctrl+S; then atgs-render renders the saved file."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from atgs.viewer.camera_path_file import load_camera_path
from atgs.viewer.cli import render_main
from atgs.timeline import frame_at
from builders import write_tiny_checkpoint

SESSION = Path(__file__).with_name("path_window_session.py")


def test_keyframes_preview_save_and_render(tmp_path: Path) -> None:
    if shutil.which("xvfb-run") is None:
        pytest.fail("xvfb-run is missing: apt-get install xvfb xauth")
    ckpt = write_tiny_checkpoint(tmp_path / "ckpt.pt", num_frames=12)  # 96x72 training cameras
    out = tmp_path / "session"
    cmd = ["xvfb-run", "-a", "-s", "-screen 0 1280x800x24", sys.executable, str(SESSION), str(ckpt), str(out),
           "--fps", "8", "--duration", "1.0"]  # no --size: the default window on a 1280x800 screen
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads((out / "report.json").read_text())
    assert report["window_size"] == [960, 720]  # a 96x72 camera no longer opens a thumbnail
    assert report["window_std"] > 5.0  # splats and UI, not a blank window

    # three keyframes, each where the view and the playhead were when K was pressed
    views, keys = report["keyframe_views"], report["editor_keys"]
    assert len(keys) == 3 and [k["video_t"] for k in keys] == [0.0, 0.5, 1.0]
    for v, k in zip(views, keys):
        np.testing.assert_allclose(k["w2c"], v["w2c"], atol=1e-12)
        assert k["scene_t"] == v["time"]
    assert keys[1]["scene_t"] > keys[0]["scene_t"] and keys[2]["scene_t"] == 1.0  # Right, then End
    assert np.abs(np.subtract(keys[0]["w2c"], keys[1]["w2c"])).max() > 0.1  # the drags moved the view

    # the saved file is what was recorded, and the preview showed exactly the frames it renders
    saved = out / "path.json"
    assert report["message"] == f"saved {saved}"
    path = load_camera_path(saved)
    assert path.size == (960, 720) and path.fps == 8.0 and path.frame_count() == 8
    for k, rk in zip(path.keys, keys):
        np.testing.assert_array_equal(k.w2c, rk["w2c"])
    cams, times = path.render_plan(960, 720)
    preview = report["preview"]
    assert [p["frame"] for p in preview] == list(range(8))  # every video frame, in order, once
    for p, cam, t in zip(preview, cams, times):
        np.testing.assert_allclose(p["w2c"], cam.w2c, atol=1e-12)
        np.testing.assert_allclose(p["K"], cam.K, atol=1e-9)
        assert p["seq_frame"] == frame_at(t, 12)

    # and atgs-render takes the saved file
    frames = tmp_path / "frames"
    assert render_main([str(ckpt), "--path", str(saved), "--out", str(frames), "--size", "96x72", "--gl", "osmesa"]) == 0
    assert len(list(frames.iterdir())) == 8
