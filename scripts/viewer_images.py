"""The player pictures of the README and docs/viewer.md: a screenshot of the real player window
with a camera path being edited, the path file, and a strip of frames that atgs-render makes
from that file.

    python scripts/viewer_images.py            # runs itself under xvfb-run when there is no display

Plays the built-in demo scene (no checkpoint needed) in the default window of a 1280x800
screen, records four keyframes through the path panel's own actions (as the K key does), saves
the path like Ctrl+S does, then renders it with ``atgs-render demo --path FILE.json``.
Writes docs/images/player_camera_path.png, docs/images/camera_path_strip.png and
docs/demo_camera_path.json (which `atgs-render demo --path docs/demo_camera_path.json` renders).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parent.parent
SCREENSHOT = ROOT / "docs/images/player_camera_path.png"
STRIP = ROOT / "docs/images/camera_path_strip.png"
PATH_FILE = ROOT / "docs/demo_camera_path.json"
STRIP_FRAMES, STRIP_SIZE = 6, (256, 192)


def record_path_and_screenshot() -> None:
    from atgs.viewer.app import PlayerApp
    from atgs.viewer.camera_path import CameraPath
    from atgs.viewer.loading import load_source

    os.chdir(ROOT)  # the panel and its messages show the file relative to the repository
    app = PlayerApp(load_source("demo"), path_file=PATH_FILE.relative_to(ROOT))
    try:
        deadline = time.monotonic() + 60
        while app.feeder.shown is None and time.monotonic() < deadline:
            app.step(0.0)
        ctl, pb, panel = app.control, app.playback, app.paths
        panel.editor.replace_path(CameraPath())  # start from an empty path
        # A fly-through: from far and high, down around the ring, close in, time playing 0 -> 1.
        for orbit, zoom, frame in (((0.0, 0.25), -1.5, 0), ((0.9, -0.2), 1.5, 40), ((0.9, -0.05), 1.0, 80),
                                   ((0.8, 0.15), -0.5, 119)):
            ctl.orbit(*orbit)
            ctl.zoom(zoom)
            pb.seek_frame(frame)
            panel.add_keyframe()
        panel.editor.set_timing(duration_s=4.0, fps=30.0)
        panel.save()
        # The screenshot: the second keyframe selected, seen from above and behind the path.
        panel.editor.selected = 1
        panel.go_to(1)
        ctl.zoom(-7.5)
        ctl.orbit(1.15, -0.4)
        ctl.pan(190, 140, 720)  # the path clear of the panels
        pb.seek_frame(40)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and (app.feeder.shown is None or app.feeder.shown.frame != 40):
            app.step(0.05)
        for _ in range(5):  # the idle full-resolution pass replaces the adaptive one
            app.step(0.05)
        shot = Image.fromarray(app.read_window())
    finally:
        app.close()
    save_small_png(shot, SCREENSHOT)


def render_strip() -> None:
    from atgs.viewer.cli import render_main

    with tempfile.TemporaryDirectory() as tmp:
        frames = Path(tmp) / "frames"
        size = f"{STRIP_SIZE[0]}x{STRIP_SIZE[1]}"
        if render_main(["demo", "--path", str(PATH_FILE), "--out", str(frames), "--frames", str(STRIP_FRAMES),
                        "--size", size]) != 0:
            sys.exit("scripts/viewer_images.py: atgs-render failed")
        tiles = [np.asarray(Image.open(p)) for p in sorted(frames.iterdir())]
    gap = np.full((STRIP_SIZE[1], 4, 3), 255, np.uint8)
    row = np.concatenate([x for t in tiles for x in (t, gap)][:-1], axis=1)
    save_small_png(Image.fromarray(row), STRIP)


def save_small_png(img: Image.Image, path: Path) -> None:
    """A 256-color PNG: a README picture at a third of the size of the full-color one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    img.convert("RGB").quantize(256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(path, optimize=True)
    print(f"wrote {path.relative_to(ROOT)} ({path.stat().st_size // 1024} kB)")


def main() -> None:
    if not os.environ.get("DISPLAY"):
        if shutil.which("xvfb-run") is None:
            sys.exit("scripts/viewer_images.py: no display and no xvfb-run; install xvfb (apt-get install xvfb)")
        sys.exit(subprocess.call(["xvfb-run", "-a", "-s", "-screen 0 1280x800x24", sys.executable, *sys.argv]))
    record_path_and_screenshot()
    render_strip()


if __name__ == "__main__":
    main()
