"""Streaming and failures of the web player in a real browser (Chromium, software WebGL2), on a
small synthetic export (atgs.web.synthetic: no training): the look-ahead window holds at most its
budget while the video plays through and a seek back fetches dropped chunks again; a lost WebGL
context is restored and the frame drawn again; a missing environment map falls back to the
background colour with a note; a chunk that fails once is fetched again; a chunk that fails
through an outage (every try of the fetcher) is fetched again after the window's wait and plays,
the error line shown meanwhile and gone after; a missing chunk is fetched again only when a seek
or Play asks for it (the page's clock faked: the waits pass in no time)."""

from __future__ import annotations

import io
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from atgs.web.browser import PlayerPage, chromium, serving
from atgs.web.synthetic import synthetic_export

FRAMES, CHUNK_FRAMES = 48, 4  # 12 chunks
BACKGROUND = (0.2, 0.4, 0.6)


@pytest.fixture(scope="module")
def export(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("stream") / "web"
    synthetic_export(out, frames=FRAMES, gaussians=300, chunk_frames=CHUNK_FRAMES, environment=True,
                     background=BACKGROUND)
    return out


@pytest.fixture(scope="module")
def browser():
    with chromium() as b:
        yield b


def _chunk_requests(page: PlayerPage) -> list[str]:
    log: list[str] = []
    page.page.on("request", lambda r: log.append(r.url.rsplit("/", 1)[-1]) if r.url.endswith(".bin") else None)
    return log


def test_two_chunks_at_most_while_playing_through_and_a_seek_back_fetches_again(export, browser):
    with serving(export) as url:
        # ahead=2: two chunks at most; budget=0.001 (1 kB): below what any stream needs, raised with a note
        page = PlayerPage(browser, url, {"camera": 0, "paused": 1, "size": "camera", "ahead": 2, "budget": 0.001})
        requests = _chunk_requests(page)
        page.first_frame()
        page.seek(9)  # chunk 2
        first_look = page.pixels()
        page.call("p.play()")
        # the last chunk's frames, then the first ones again (loop): the whole video went past
        page.page.wait_for_function(f"() => window.atgsPlayer.state().frame >= {FRAMES - CHUNK_FRAMES}")
        page.page.wait_for_function(f"() => window.atgsPlayer.state().frame < {CHUNK_FRAMES}")
        page.call("p.pause()")
        s = page.state()
        assert s["error"] is None, page.console
        assert s["maxChunks"] == 2 and s["peakHeldChunks"] <= 2 and s["heldChunks"] <= 2, s
        assert s["budgetBytes"] == s["minimumBytes"] > 1000 and s["peakHeldBytes"] <= s["windowBudgetBytes"]
        assert s["note"].startswith("URL parameter budget=0.001: this stream needs")
        assert s["downloads"] >= FRAMES // CHUNK_FRAMES
        assert len(requests) == s["downloads"]  # the page's count is the network's
        assert requests.count("chunk_000002.bin") == 1
        page.seek(9)  # chunk 2 was dropped long ago: from the network again, the same picture
        assert requests.count("chunk_000002.bin") == 2
        np.testing.assert_array_equal(page.pixels(), first_look)
        assert page.state()["peakHeldChunks"] <= 2
        page.close()


def _canvas_shot(page: PlayerPage) -> np.ndarray:
    png = page.page.locator("#view").screenshot()
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), np.float32) / 255.0


def test_a_lost_webgl_context_is_restored_and_the_frame_drawn_again(export, browser):
    with serving(export) as url:
        page = PlayerPage(browser, url, {"camera": 0, "paused": 1, "size": "camera"})
        page.first_frame()
        page.seek(6)
        before, shot_before = page.pixels(), _canvas_shot(page)
        assert float(before.std()) > 0.02  # a picture, not a flat colour
        page.page.evaluate("() => { window.loseContext = document.getElementById('view')"
                           ".getContext('webgl2').getExtension('WEBGL_lose_context'); "
                           "window.loseContext.loseContext(); }")
        page.page.wait_for_function("() => window.atgsPlayer.state().contextLost")
        drawn = page.state()["framesDrawn"]
        page.page.evaluate("() => window.loseContext.restoreContext()")
        page.page.wait_for_function(f"() => {{ const s = window.atgsPlayer.state(); "
                                    f"return !s.contextLost && s.contextRestores === 1 && s.framesDrawn > {drawn}; }}")
        shot_after, after = _canvas_shot(page), page.pixels()
        assert np.abs(after - before).max() <= 1 / 255
        assert np.abs(shot_after - shot_before).max() <= 2 / 255  # drawn again by the player itself
        assert page.state()["error"] is None
        page.close()


def test_a_missing_environment_map_falls_back_to_the_background_colour_with_a_note(export, browser, tmp_path):
    corner = np.array(BACKGROUND)
    with serving(export) as url:  # with the map: the corner shows it, not the background colour
        page = PlayerPage(browser, url, {"camera": 0, "paused": 1, "size": "camera"})
        page.first_frame()
        assert np.abs(page.pixels()[0, 0] - corner).max() > 0.05
        assert page.state()["note"] is None
        page.close()
    broken = tmp_path / "no-env"
    shutil.copytree(export, broken)
    (broken / "stream" / "environment.png").unlink()
    with serving(broken) as url:
        page = PlayerPage(browser, url, {"camera": 0, "paused": 1, "size": "camera"})
        page.first_frame()
        note = page.page.locator("#note")
        assert note.is_visible()
        assert "environment.png is missing (HTTP 404)" in note.inner_text()
        assert "background colour" in note.inner_text()
        got = page.pixels()
        np.testing.assert_allclose(got[0, 0], corner, atol=1 / 255)
        assert float(got.std()) > 0.02
        s = page.state()
        assert s["error"] is None and page.page.locator("#error").is_hidden()
        page.seek(20)  # it plays on
        page.close()


def test_a_chunk_that_fails_once_is_fetched_again(export, browser):
    with serving(export) as url:
        failures = []

        def once(route):
            if not failures:
                failures.append(route.request.url)
                route.fulfill(status=503, body="busy")
            else:
                route.continue_()

        # (routed before the page loads: the look-ahead may ask for chunk 3 at once)
        page = PlayerPage(browser, url, {"camera": 0, "paused": 1, "size": "camera"},
                          routes=[("**/chunk_000003.bin", once)])
        page.first_frame()
        page.seek(13)  # chunk 3: 503 (now or when prefetched), then after the back-off (0.25-0.5 s) the file
        assert len(failures) == 1
        s = page.state()
        assert s["frame"] == 13 and s["error"] is None
        page.close()


def _run_until(page: PlayerPage, condition: str, step_ms: int, steps: int) -> None:
    """Move the page's paused clock by step_ms until `condition` (a JS expression of ``s``, the
    player's state) holds; the network answers in real time in between."""
    for _ in range(steps):
        page.page.clock.run_for(step_ms)
        if page.page.evaluate(f"() => {{ const s = window.atgsPlayer.state(); return {condition}; }}"):
            return
        time.sleep(0.02)
    raise AssertionError(f"{condition} never held: {page.state()}, {page.console}")


def _pause_clock(page: PlayerPage) -> None:
    page.page.clock.pause_at(page.page.evaluate("Date.now()") / 1000 + 1)  # from here time moves by run_for


def test_playback_waits_out_an_outage_and_draws_the_chunk_once_the_network_is_back(export, browser):
    with serving(export) as url:
        net = {"down": True, "requests": 0}

        def outage(route):
            net["requests"] += 1
            if net["down"]:
                route.abort("internetdisconnected")
            else:
                route.continue_()

        page = PlayerPage(browser, url, {"camera": 0, "paused": 1, "size": "camera", "frame": 16},
                          fake_clock=True, routes=[("**/chunk_000005.bin", outage)])
        page.first_frame()
        _pause_clock(page)
        page.call("p.play()")
        # frames 16-19 play, then chunk 5 (frame 20) fails: the fetcher's 5 tries (0.25-4 s apart),
        # then the window waits 5 s before the next round; playback holds at frame 19 meanwhile
        _run_until(page, "s.frame === 19 && s.buffering && s.playing && /trying again in/.test(s.error ?? '')", 500, 60)
        line = page.page.locator("#error")
        assert line.is_visible()
        assert "chunk_000005.bin" in line.inner_text() and "5 tries" in line.inner_text(), line.inner_text()
        tried = net["requests"]
        assert tried == 5  # one round of the fetcher's tries
        page.page.clock.run_for(3000)  # within the window's 5 s wait: no request
        page.state()
        assert net["requests"] == tried
        net["down"] = False
        # the next round (at most 2 s of the wait left) loads it: playback goes on from frame 20
        _run_until(page, "s.frame >= 20 && !s.buffering", 100, 100)
        page.call("p.pause()")
        s = page.state()
        assert 20 <= s["frame"] <= 23 and s["error"] is None, s  # drawn from chunk 5, the line gone
        assert line.is_hidden()
        assert net["requests"] == tried + 1
        drawn, frame = page.pixels(), s["frame"]
        page.close()
        # the same frame on a page that never saw the outage: the same picture
        clean = PlayerPage(browser, url, {"camera": 0, "paused": 1, "size": "camera", "frame": frame})
        clean.first_frame()
        assert clean.state()["frame"] == frame
        np.testing.assert_allclose(drawn, clean.pixels(), atol=1 / 255)
        assert float(drawn.std()) > 0.02  # a picture, not a flat colour
        clean.close()


def test_a_missing_chunk_is_not_fetched_again_unless_a_seek_or_play_asks_for_it(export, browser):
    with serving(export) as url:
        requests = []

        def missing(route):
            requests.append(route.request.url)
            route.fulfill(status=404, body="gone")

        page = PlayerPage(browser, url, {"camera": 0, "paused": 1, "size": "camera", "frame": 16},
                          fake_clock=True, routes=[("**/chunk_000005.bin", missing)])
        page.first_frame()
        assert "chunk_000005.bin is missing (HTTP 404)" in page.error_text()
        page.page.wait_for_function("() => window.atgsPlayer.state().windowFull")  # nothing in flight
        _pause_clock(page)
        page.call("p.play()")  # asks for chunk 4, where it is: chunk 5 is not asked for
        _run_until(page, "!s.playing", 100, 50)  # stopped at the missing chunk
        for _ in range(10):  # ten minutes of the page's time
            page.page.clock.run_for(60_000)
            page.state()
        s = page.state()
        assert s["frame"] == 19 and not s["playing"] and "missing" in s["error"], s
        assert len(requests) == 1
        page.call("p.play()")  # Play at the missing chunk asks for it: once more
        _run_until(page, "!s.playing", 100, 50)
        assert len(requests) == 2
        page.page.evaluate("() => { window.atgsPlayer.seek(22).catch(() => {}); }")  # a seek onto it: once more
        for _ in range(10):
            page.page.clock.run_for(60_000)
            page.state()
        assert len(requests) == 3
        assert page.page.locator("#error").is_visible()
        page.close()
