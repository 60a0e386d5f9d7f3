"""A scripted camera-path session in the real player window (run under xvfb-run by
test_camera_path_window.py): three keyframes added with the K key between mouse drags and
playhead moves, a preview started with V, the path saved with Ctrl+S. Writes a JSON report.

usage: python tests/path_window_session.py CKPT OUT_DIR [--size WxH]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from atgs.viewer.app import PlayerApp
from atgs.viewer.loading import load_source


def press(app: PlayerApp, key, ctrl: bool = False) -> None:
    """A key press and release through imgui's input queue, as the glfw backend feeds it."""
    io, K = app.imgui.get_io(), app.imgui.Key
    if ctrl:
        io.add_key_event(K.mod_ctrl, True)
    io.add_key_event(key, True)
    app.step(0.0)
    io.add_key_event(key, False)
    if ctrl:
        io.add_key_event(K.mod_ctrl, False)
    app.step(0.0)


def drag(app: PlayerApp, dx: float, dy: float) -> None:
    """Left-button drag across the middle of the window (orbits the view)."""
    io, glfw = app.imgui.get_io(), app.glfw
    w, h = glfw.get_window_size(app.window)
    x, y = w / 2, h / 2

    def move_to(px: float, py: float) -> None:
        glfw.set_cursor_pos(app.window, px, py)  # the backend also tracks the real cursor
        io.add_mouse_pos_event(px, py)
        for _ in range(2):  # X delivers the warp's motion event a UI frame later: let it arrive
            app.step(0.0)

    move_to(x, y)
    io.add_mouse_button_event(0, True)
    app.step(0.0)
    move_to(x + dx, y + dy)
    io.add_mouse_button_event(0, False)
    app.step(0.0)


def session(app: PlayerApp, fps: float, duration_s: float) -> dict:
    K = app.imgui.Key
    deadline = time.monotonic() + 60.0
    while app.feeder.shown is None and time.monotonic() < deadline:  # first frame decoded
        app.step(0.0)
    press(app, K.h)  # hide the UI: the mouse reaches the view (the path panel stays usable by keys)
    views = []
    for move in ((None, None), ((60.0, 0.0), K.right_arrow), ((-40.0, 15.0), K.end)):
        drag_by, key = move
        if drag_by is not None:
            drag(app, *drag_by)
            press(app, key)
        press(app, K.k)
        views.append({"w2c": app.control.camera(8, 8).w2c.tolist(), "time": app.playback.time})
    press(app, K.h)
    ed = app.paths.editor
    ed.set_timing(duration_s=duration_s, fps=fps)
    press(app, K.v)  # preview: the first frame is on screen after this UI frame
    fb_w, fb_h = app.glfw.get_framebuffer_size(app.window)
    shown = []
    while ed.previewing:
        cam = app.control.camera(fb_w, fb_h)
        shown.append({"frame": ed.frame, "w2c": cam.w2c.tolist(), "K": cam.K.tolist(),
                      "seq_frame": app.playback.frame})
        app.step(1.0 / fps)  # one video frame of wall time per UI frame
    press(app, K.s, ctrl=True)
    return {
        "window_size": [fb_w, fb_h],
        "keyframe_views": views,
        "editor_keys": [{"video_t": k.video_t, "scene_t": k.scene_t, "w2c": k.w2c.tolist()} for k in ed.keys],
        "preview": shown,
        "message": app.message,
        "window_std": float(np.asarray(app.read_window(), dtype=np.float64).std()),
    }


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("checkpoint")
    ap.add_argument("out_dir", type=Path)
    ap.add_argument("--size", default=None)
    ap.add_argument("--fps", type=float, default=8.0)
    ap.add_argument("--duration", type=float, default=1.0)
    args = ap.parse_args()
    args.out_dir.mkdir(parents=True, exist_ok=True)
    app = PlayerApp(load_source(args.checkpoint), size=args.size, path_file=args.out_dir / "path.json")
    try:
        report = session(app, args.fps, args.duration)
    finally:
        app.close()
    (args.out_dir / "report.json").write_text(json.dumps(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
