"""Every control of the web player in a real browser (Debian's Chromium, software WebGL2): the
buttons, the scrub bar, the menus, the mouse, touch (multi-touch through CDP) and the keyboard,
each judged by the frame index the page reports or by the pixels it drew.

The stream is written by hand (no training): a white Gaussian at the orbit centre, three small
coloured ones beside it and a yellow one circling below, over black, seen by four cameras that
look at the centre. So the white blob's centroid sits where the centre projects (a pan moves it
by exactly the pointer's motion) and its area scales with the inverse square of the camera's
distance (a zoom by factor f scales it by 1 / f^2)."""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest

from atgs.cameras import Camera
from atgs.web.browser import PlayerPage, chromium, serving
from atgs.web.export import STREAM_DIR, copy_player
from atgs.web.manifest import FORMAT, MANIFEST_NAME, VERSION, ChunkInfo, camera_entry, chunk_file_name, render_numerics
from atgs.web.stream_format import StreamFrame, pack_chunk, quantize_chunk

FRAMES, CHUNK_FRAMES, FPS = 12, 4, 30.0
WIDTH, HEIGHT, FOCAL = 160, 120, 100.0
CAMERA_HEIGHT = 1.0
DISTANCE = math.hypot(4.0, CAMERA_HEIGHT)  # every camera's distance to the centre (the origin)
WHEEL_PIXELS = 300                          # one wheel event: the view's distance times e^(+-0.3)
SAME = 3 / 255                              # a view and its inverse draw the same image to this


def _look_at_origin(name: str, azimuth: float) -> Camera:
    """A camera 4 from the z axis at height 1, looking at the origin, world z up (image up)."""
    c = np.array([4.0 * math.cos(azimuth), 4.0 * math.sin(azimuth), CAMERA_HEIGHT])
    forward = -c / np.linalg.norm(c)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    w2c = np.eye(4)
    w2c[:3, :3] = np.stack([right, down, forward])
    w2c[:3, 3] = -w2c[:3, :3] @ c
    K = [[FOCAL, 0, WIDTH / 2], [0, FOCAL, HEIGHT / 2], [0, 0, 1]]
    return Camera(name, WIDTH, HEIGHT, K, w2c)


def _frame(k: int) -> StreamFrame:
    turn = 2 * math.pi * k / FRAMES
    means = [[0, 0, 0], [0.3, 0.7, 0], [0.3, -0.7, 0], [0.3, 0, 0.7], [math.cos(turn), math.sin(turn), -0.7]]
    colors = [[0.9, 0.9, 0.9], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0]]
    sigma = [0.25, 0.1, 0.1, 0.1, 0.1]
    n = len(means)
    return StreamFrame(np.arange(n), np.array(means, float), np.repeat(np.array(sigma)[:, None], 3, 1),
                       np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 0.95), np.array(colors, float))


@pytest.fixture(scope="module")
def url(tmp_path_factory):
    """The hand-made stream, written as atgs-export writes one, served for the module."""
    out = tmp_path_factory.mktemp("controls")
    (out / STREAM_DIR).mkdir()
    chunks = []
    for i, start in enumerate(range(0, FRAMES, CHUNK_FRAMES)):
        q = quantize_chunk([_frame(k) for k in range(start, start + CHUNK_FRAMES)])
        data = pack_chunk(q)
        (out / STREAM_DIR / chunk_file_name(i)).write_bytes(data)
        chunks.append(asdict(ChunkInfo(chunk_file_name(i), CHUNK_FRAMES, q.num_gaussians, q.static, len(data))))
    cameras = [_look_at_origin(f"cam{i}", i * math.pi / 2) for i in range(4)]
    manifest = {"format": FORMAT, "version": VERSION, "fps": FPS, "frames": list(range(FRAMES)),
                "chunk_frames": CHUNK_FRAMES, "chunks": chunks,
                "cameras": [camera_entry(c, held_out=False) for c in cameras], "background": [0.0, 0.0, 0.0],
                "environment": None, "render": render_numerics(),
                "scene": {"center": [0.0, 0.0, 0.0], "radius": DISTANCE},
                "source": {"test": "tests/test_web_controls.py"}}
    (out / STREAM_DIR / MANIFEST_NAME).write_text(json.dumps(manifest))
    copy_player(out)
    with serving(out) as u:
        yield u


@pytest.fixture(scope="module")
def browser():
    with chromium() as b:
        yield b


# --- what the pixels say --------------------------------------------------------------------------
def _white(px: np.ndarray) -> np.ndarray:
    """The white blob's pixels (the coloured ones lack at least one channel)."""
    return px.min(axis=-1) > 0.4


def _area(px: np.ndarray) -> int:
    return int(_white(px).sum())


def _centroid(px: np.ndarray) -> np.ndarray:
    """(x, y) of the white blob's centroid, in pixel-centre coordinates."""
    ys, xs = np.nonzero(_white(px))
    assert xs.size > 20, "the white blob is not in the picture"
    return np.array([xs.mean() + 0.5, ys.mean() + 0.5])


def _diff(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).max())


def _same(a: np.ndarray, b: np.ndarray) -> None:
    """The same picture, to 3 levels of 255 (a view and its inverse)."""
    d = _diff(a, b)
    assert d <= SAME, f"the pictures differ by up to {d * 255:.0f} / 255"


def _changed(a: np.ndarray, b: np.ndarray) -> None:
    d = _diff(a, b)
    assert d > 0.3, f"the picture barely changed ({d * 255:.0f} / 255)"


class Session:
    """One player page on camera 0 at the camera's pixel size (the canvas at the window's top left)."""

    def __init__(self, browser, url, **kw):
        self.p = PlayerPage(browser, url, {"camera": 0, "paused": 1, "size": "camera"}, **kw)
        self.page = self.p.page
        self.p.first_frame()

    def drawn(self) -> np.ndarray:
        """The picture once the page has drawn what the input so far asks for: two animation
        frames later the player's tick has run at least once after it."""
        self.page.evaluate("() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))")
        return self.p.pixels()

    def state(self) -> dict:
        return self.p.state()

    def wait_frame(self, frame: int) -> None:
        self.page.wait_for_function("f => window.atgsPlayer.state().frame === f", arg=frame)

    def drag(self, x0, y0, x1, y1, button="left", steps=5):
        m = self.page.mouse
        m.move(x0, y0)
        m.down(button=button)
        m.move(x1, y1, steps=steps)
        m.up(button=button)

    def touch(self, kind: str, points: list[tuple[float, float]], ids: list[int] | None = None) -> None:
        """A CDP touch event (ids 0, 1, ... unless given): Start and Move list every finger on the
        glass after it, End the fingers that lift (none: all of them)."""
        if not hasattr(self, "cdp"):
            self.cdp = self.page.context.new_cdp_session(self.page)
        ids = ids if ids is not None else list(range(len(points)))
        self.cdp.send("Input.dispatchTouchEvent", {"type": f"touch{kind}", "touchPoints": [
            {"x": x, "y": y, "id": i} for (x, y), i in zip(points, ids)]})

    def swipe(self, start: list[tuple[float, float]], end: list[tuple[float, float]], steps: int = 5) -> None:
        """Fingers land at ``start``, move in a straight line to ``end`` and lift."""
        self.touch("Start", start)
        for s in range(1, steps + 1):
            t = s / steps
            self.touch("Move", [(x0 + t * (x1 - x0), y0 + t * (y1 - y0)) for (x0, y0), (x1, y1) in zip(start, end)])
        self.touch("End", [])

    def close(self):
        self.p.close()


# --- playback ------------------------------------------------------------------------------------
def test_play_pause_speed_loop_and_the_scrub_bar(browser, url):
    s = Session(browser, url, fake_clock=True)
    for f in (5, 9, 0):  # every chunk decoded: playback below never waits for the network
        s.p.seek(f)
    page, clock = s.page, s.page.clock
    clock.pause_at(page.evaluate("Date.now()") / 1000 + 1)  # from here the page's time moves only by run_for

    def seek(frame):
        """The player's seek waits for a draw, and draws need ticks; a chunk the byte budget let go
        is fetched and decoded again in real time (the fake clock does not move the network), and
        the next chunk's decode, started on arrival, is given real time to finish too."""
        page.evaluate("f => { window.atgsPlayer.seek(f); }", frame)
        for _ in range(200):
            clock.run_for(50)
            if s.state()["frame"] == frame and not s.state()["buffering"]:
                break
            time.sleep(0.02)
        assert s.state()["frame"] == frame
        time.sleep(0.3)

    def played(speed: str, ms: int) -> int:
        """Frames advanced from frame 0 by playing `ms` at `speed` (loop off)."""
        page.select_option("#speed", speed)
        seek(0)
        page.click("#play")
        clock.run_for(ms)
        page.click("#play")
        assert not s.state()["playing"]
        return s.state()["frame"]

    # play and pause by the button: frames advance, then hold over time
    page.click("#play")
    assert s.state()["playing"] and page.inner_text("#play") == "Pause"
    clock.run_for(200)  # 6 frames at 30 fps
    assert s.state()["frame"] > 0
    page.click("#play")
    held = s.state()["frame"]
    clock.run_for(1000)
    assert s.state()["frame"] == held and not s.state()["playing"] and page.inner_text("#play") == "Play"

    # speed: 150 ms at 0.5x, 1x and 2x are about 2, 4 and 9 frames (loop off: no wrap-around)
    page.click("#loop")
    assert s.state()["loop"] is False
    half, one, two = played("0.5", 150), played("1", 150), played("2", 150)
    assert s.state()["speed"] == 2
    assert 0 < half < one < two, (half, one, two)
    assert 1.5 <= two / one <= 2.5, (one, two)

    # loop off: playing past the end stops at the last frame
    seek(9)
    page.click("#play")
    clock.run_for(500)
    assert s.state()["frame"] == FRAMES - 1 and not s.state()["playing"]
    # loop on: it wraps around and plays on
    page.click("#loop")
    page.select_option("#speed", "1")
    seek(9)
    page.click("#play")
    clock.run_for(200)  # 9 + 6 = 15 frames: frame 3 of the next pass
    state = s.state()
    assert state["playing"] and state["loop"] and state["frame"] < 9, state
    page.click("#play")

    # the scrub bar by pointer: its middle is the middle frame, its right end the last
    box = page.locator("#scrub").bounding_box()
    x0, x1, y = box["x"], box["x"] + box["width"], box["y"] + box["height"] / 2
    page.mouse.click((x0 + x1) / 2, y)
    clock.run_for(50)
    assert abs(s.state()["frame"] - (FRAMES - 1) / 2) <= 1.0, s.state()
    s.drag((x0 + x1) / 2, y, x1 + 20, y)
    clock.run_for(50)
    assert s.state()["frame"] == FRAMES - 1
    # dragged while playing (loop on), playback holds under the pointer and goes on after it
    page.click("#play")
    page.mouse.move(x0 + 0.25 * (x1 - x0), y)
    page.mouse.down()
    clock.run_for(200)
    state = s.state()
    assert not state["playing"] and abs(state["frame"] - (FRAMES - 1) / 4) <= 1.0, state
    page.mouse.up()
    clock.run_for(100)
    assert s.state()["playing"] and s.state()["frame"] > state["frame"]
    page.click("#play")
    assert s.state()["error"] in (None, "")
    s.close()


# --- mouse, wheel and the camera menu ----------------------------------------------------------------
def test_mouse_orbit_pan_wheel_and_the_camera_menu(browser, url):
    s = Session(browser, url)
    page = s.page
    home = s.drawn()
    cx, cy = WIDTH / 2, HEIGHT / 2
    # the white blob sits where the orbit centre projects: the principal point
    assert np.allclose(_centroid(home), [cx, cy], atol=0.5), _centroid(home)

    # orbit: a drag right turns the scene, the drag back restores it
    s.drag(cx, cy, cx + 40, cy)
    turned = s.drawn()
    _changed(turned, home)
    assert s.state()["camera"] is None and page.input_value("#camera") == "free"
    s.drag(cx + 40, cy, cx, cy)
    _same(s.drawn(), home)

    # pan (right-drag, then shift-drag back): the centre follows the pointer exactly
    s.drag(cx, cy, cx + 20, cy + 10, button="right")
    panned = s.drawn()
    assert np.allclose(_centroid(panned) - _centroid(home), [20, 10], atol=1.0), _centroid(panned)
    page.keyboard.down("Shift")
    s.drag(cx + 20, cy + 10, cx, cy)
    page.keyboard.up("Shift")
    _same(s.drawn(), home)

    # wheel: one event of -300 px brings the camera to e^-0.3 of its distance (the blob's area
    # grows by e^0.6), +300 px takes it back
    page.mouse.move(cx, cy)
    page.mouse.wheel(0, -WHEEL_PIXELS)
    ratio = _area(s.drawn()) / _area(home)
    assert abs(ratio / math.exp(0.6) - 1) < 0.15, ratio
    page.mouse.wheel(0, WHEEL_PIXELS)
    _same(s.drawn(), home)

    # the camera menu shows a training camera exactly, and back
    page.select_option("#camera", "2")
    other = s.drawn()
    assert s.state()["camera"] == 2
    _changed(other, home)
    page.select_option("#camera", "0")
    assert s.state()["camera"] == 0
    _same(s.drawn(), home)
    assert s.state()["error"] in (None, "")
    s.close()


# --- touch -----------------------------------------------------------------------------------------
def test_touch_orbit_two_finger_pan_pinch_and_no_jump(browser, url):
    s = Session(browser, url, touch=True)
    home = s.drawn()
    cx, cy = WIDTH / 2, HEIGHT / 2
    # the mouse's orbit by 20 px, the reference for the fingers'
    s.drag(cx, cy, cx + 20, cy)
    orbit20 = s.drawn()
    s.drag(cx + 20, cy, cx, cy)
    _same(s.drawn(), home)

    # one finger orbits as the mouse does
    s.swipe([(cx, cy)], [(cx + 20, cy)])
    _same(s.drawn(), orbit20)
    s.swipe([(cx + 20, cy)], [(cx, cy)])
    _same(s.drawn(), home)

    # a second finger landing and lifting mid-drag moves nothing: the first finger's 10 + 10 px
    # are the mouse's 20
    s.touch("Start", [(40, cy)])
    s.touch("Move", [(50, cy)])
    s.touch("Start", [(50, cy), (140, 30)], ids=[0, 1])
    s.touch("End", [(140, 30)], ids=[1])
    s.touch("Move", [(55, cy)])
    s.touch("Move", [(60, cy)])
    s.touch("End", [])
    _same(s.drawn(), orbit20)
    s.swipe([(cx + 20, cy)], [(cx, cy)])
    _same(s.drawn(), home)

    # two fingers moving together pan by their motion, without zooming
    s.swipe([(60, 50), (100, 70)], [(72, 58), (112, 78)])
    panned = s.drawn()
    assert np.allclose(_centroid(panned) - _centroid(home), [12, 8], atol=1.0), _centroid(panned)
    assert abs(_area(panned) / _area(home) - 1) < 0.1
    s.swipe([(72, 58), (112, 78)], [(60, 50), (100, 70)])
    _same(s.drawn(), home)

    # a pinch spreading the fingers from 20 to 40 px about the centre halves the distance: the
    # blob's area grows by 4 and it stays where it was
    s.swipe([(cx - 10, cy), (cx + 10, cy)], [(cx - 20, cy), (cx + 20, cy)])
    zoomed = s.drawn()
    assert abs(_area(zoomed) / _area(home) / 4 - 1) < 0.15, _area(zoomed) / _area(home)
    assert np.allclose(_centroid(zoomed), _centroid(home), atol=1.0)
    s.swipe([(cx - 20, cy), (cx + 20, cy)], [(cx - 10, cy), (cx + 10, cy)])
    _same(s.drawn(), home)
    assert s.state()["error"] in (None, "")
    s.close()


# --- keyboard --------------------------------------------------------------------------------------
def test_the_keyboard_on_the_focused_canvas(browser, url):
    s = Session(browser, url)
    page, key = s.page, s.page.keyboard.press
    home = s.drawn()
    # Tab reaches the canvas first, and the focus is visible
    key("Tab")
    focus = page.evaluate("""() => { const c = document.activeElement, st = getComputedStyle(c);
        return {id: c.id, visible: c.matches(':focus-visible'), outline: st.outlineStyle, width: st.outlineWidth}; }""")
    assert focus == {"id": "view", "visible": True, "outline": "solid", "width": "3px"}, focus

    # frames: . and , step, End and Home go to the ends, 5 to the middle
    key(".")
    s.wait_frame(1)
    key(".")
    s.wait_frame(2)
    key(",")
    s.wait_frame(1)
    key("End")
    s.wait_frame(FRAMES - 1)
    key("Home")
    s.wait_frame(0)
    key("5")
    s.wait_frame(6)  # Math.round(0.5 * 11)
    key("Home")
    s.wait_frame(0)

    # space plays and pauses; L, [ and ] set loop and speed
    key(" ")
    assert s.state()["playing"]
    key(" ")
    assert not s.state()["playing"]
    key("Home")
    s.wait_frame(0)
    key("l")
    assert s.state()["loop"] is False
    key("l")
    assert s.state()["loop"] is True
    key("]")
    assert s.state()["speed"] == 1.5
    key("[")
    key("[")
    assert s.state()["speed"] == 0.5
    key("]")

    # the view: arrows orbit and undo, + and - zoom by 1.25 (area by 1.5625), shift+arrows pan by
    # 5 % of the canvas height, R goes back to the menu's camera, C to the next one
    home = s.drawn()
    key("ArrowRight")
    _changed(s.drawn(), home)
    key("ArrowLeft")
    _same(s.drawn(), home)
    key("+")
    ratio = _area(s.drawn()) / _area(home)
    assert abs(ratio / 1.25**2 - 1) < 0.15, ratio
    key("-")
    _same(s.drawn(), home)
    key("Shift+ArrowRight")
    key("Shift+ArrowDown")
    moved = _centroid(s.drawn()) - _centroid(home)
    assert np.allclose(moved, [0.05 * HEIGHT, 0.05 * HEIGHT], atol=1.0), moved
    key("ArrowUp")
    key("r")
    assert s.state()["camera"] == 0
    _same(s.drawn(), home)
    key("c")
    assert s.state()["camera"] == 1 and page.input_value("#camera") == "1"

    # ? opens the help, which lists the keys
    key("?")
    assert page.evaluate("document.getElementById('help').open")
    assert "play / pause" in page.inner_text("#help-keys")
    assert s.state()["error"] in (None, "")
    s.close()
