"""Test-only driver of the real player window (run under Xvfb by tests/test_viewer_window.py).

    python tests/viewer_driver.py CKPT SHOT.png [--camera I] [--size WxH] [--frames N] [--decode gl]

Opens atgs.viewer.app.PlayerApp on a checkpoint, plays, scrubs, feeds keyboard and mouse events
through imgui's input queue, saves a screenshot to SHOT.png and a JSON report to SHOT.json.
Scripted input is test scaffolding: it is not part of the atgs-view command line.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from atgs.io.cli import run_cli
from atgs.viewer.app import PlayerApp, rest_until
from atgs.viewer.loading import load_source
from atgs.viewer.output import save_image


def exercise_inputs(app: PlayerApp) -> dict:
    """Feed keyboard and mouse events through imgui's input queue (as the glfw backend does) and
    record what each did; used by the Xvfb test to check the shortcuts and mouse controls."""
    io = app.imgui.get_io()
    K = app.imgui.Key
    pb, ctl = app.playback, app.control

    def press(key) -> None:
        io.add_key_event(key, True)
        app.step(0.0)
        io.add_key_event(key, False)
        app.step(0.0)

    out: dict = {}
    f0 = pb.frame
    press(K.right_arrow)
    out["right_arrow_step"] = (pb.frame - f0) % pb.num_frames
    press(K.left_arrow)
    out["left_arrow_back"] = pb.frame == f0
    press(K.space)
    out["space_plays"] = pb.playing
    press(K.space)
    out["space_pauses"] = not pb.playing
    press(K._2)
    out["key2_mode"] = app.settings.mode
    press(K._3)
    out["key3_mode"] = app.settings.mode
    press(K._1)
    press(K.equal)
    out["speed_after_equal"] = pb.speed
    press(K.minus)
    press(K.c)
    out["camera_after_c"] = app.cam_index
    press(K.r)
    out["reset_restores_home"] = bool(np.allclose(ctl.state.eye, ctl.home.eye) and np.allclose(ctl.state.R, ctl.home.R))  # type: ignore[union-attr]
    press(K.f)
    out["fly_mode"] = app.fly_mode
    eye, fwd = ctl.state.eye.copy(), ctl.forward
    io.add_key_event(K.w, True)
    for _ in range(3):
        app.step(0.1)
    io.add_key_event(K.w, False)
    app.step(0.0)
    out["w_moves_forward"] = float((ctl.state.eye - eye) @ fwd)
    press(K.f)
    press(K.r)
    press(K.h)  # hide the panel so the mouse reaches the view
    out["ui_hidden"] = not app.show_ui
    w, h = app.glfw.get_window_size(app.window)
    eye = ctl.state.eye.copy()
    pivot = ctl.pivot.copy()
    # The glfw backend polls the real cursor of a focused window every frame, so move that one.
    app.glfw.set_cursor_pos(app.window, w / 2, h / 2)
    io.add_mouse_pos_event(w / 2, h / 2)
    app.step(0.0)
    io.add_mouse_button_event(0, True)
    app.step(0.0)
    app.glfw.set_cursor_pos(app.window, w / 2 + 40, h / 2)
    io.add_mouse_pos_event(w / 2 + 40, h / 2)
    app.step(0.0)
    io.add_mouse_button_event(0, False)
    app.step(0.0)
    out["drag_orbit_moved_eye"] = float(np.linalg.norm(ctl.state.eye - eye))
    out["drag_orbit_kept_pivot"] = float(np.linalg.norm(ctl.pivot - pivot))
    d0 = ctl.state.distance
    io.add_mouse_wheel_event(0.0, 1.0)
    app.step(0.0)
    out["wheel_zoom_ratio"] = ctl.state.distance / d0
    press(K.h)
    out["ui_shown_again"] = app.show_ui
    press(K.r)
    return out


def autotest(app: PlayerApp, screenshot: Path, frames: int) -> dict:
    """Scripted session: play ``frames`` UI frames, scrub to t = 0.75, orbit, screenshot.

    Writes ``screenshot`` (the window: splats + UI) and ``<screenshot>.json`` with what happened.
    """
    pb = app.playback
    dt = 1.0 / max(pb.fps, 1e-6)
    deadline = time.monotonic() + 60.0
    app.step(0.0)
    while app.feeder.shown is None and time.monotonic() < deadline:  # startup: first frame decoded
        app.step(0.0)
    app.stats.shown_frames.clear()
    pb.playing = True
    steps = 0
    # Play `frames` UI frames; on a loaded machine keep playing until the shown frame moved.
    playhead: list[int] = [pb.frame]  # where the playhead was before each step, then after the last
    while steps < frames or (len(set(app.stats.shown_frames)) < 2 and time.monotonic() < deadline):
        t_step = time.perf_counter()
        app.step(dt)
        rest_until(t_step + dt)  # real-time pacing, as run() does, so decoding gets its share
        playhead.append(pb.frame)  # step() advanced the playhead and then picked a frame to show
        steps += 1
    played = list(app.stats.shown_frames)
    pb.playing = False
    pb.seek_time(0.75)
    target = pb.frame
    deadline = time.monotonic() + 30.0
    while (app.feeder.shown is None or app.feeder.shown.frame != target) and time.monotonic() < deadline:
        app.step(0.0)
    inputs = exercise_inputs(app)
    app.control.orbit(0.3, 0.1)
    app.step(0.0)
    img = app.read_window()
    save_image(screenshot, img)
    splat = app.screenshot(screenshot.with_name(screenshot.stem + "_splats.png"))
    report = {
        "played_frames": played,
        "play_steps": steps,
        "playhead_frames": playhead,
        "distinct_played": len(set(played)),
        "scrub_target": target,
        "scrub_shown": None if app.feeder.shown is None else app.feeder.shown.frame,
        "window_size": list(app.glfw.get_framebuffer_size(app.window)),
        "gl": app.gl_info,
        "gaussians": app.renderer.count,
        "drawn": app.renderer.drawn_count(),
        "fps": app.stats.fps,
        "screenshot": str(screenshot),
        "splats_screenshot": str(splat),
        "inputs": inputs,
    }
    screenshot.with_suffix(".json").write_text(json.dumps(report, indent=2))
    return report


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("checkpoint")
    p.add_argument("screenshot", type=Path)
    p.add_argument("--camera", type=int, default=0)
    p.add_argument("--size", default=None)
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--decode", default="torch", choices=["torch", "gl"])
    a = p.parse_args(argv)

    def body() -> None:
        app = PlayerApp(load_source(a.checkpoint), camera_index=a.camera, size=a.size, decode=a.decode)
        try:
            print(json.dumps(autotest(app, a.screenshot, a.frames)))
        finally:
            app.close()

    return run_cli("viewer_driver", body)


if __name__ == "__main__":
    sys.exit(main())
