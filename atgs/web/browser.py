"""The web player in a headless browser: Debian's Chromium driven by Playwright (tests, bench/web.py).

Playwright downloads no browser here: it starts the system's Chromium (``executable_path``), with
software WebGL2 (SwiftShader) and the background networking off (a closed network refuses it).
:class:`PlayerPage` talks to the page through ``window.atgsPlayer`` (atgs/web/player/player.js)
and reads the canvas back as the browser drew it."""

from __future__ import annotations

import base64
import shutil
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

CHROMIUM_ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]


class BrowserUnavailable(RuntimeError):
    """No Chromium or no Playwright: the one line says what to install."""


def chromium_path() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    raise BrowserUnavailable("no Chromium found; install it with: sudo apt-get install chromium "
                             "(./scripts/test.sh does)")


@contextmanager
def serving(folder: str | Path) -> Iterator[str]:
    """Serve ``folder`` on a free localhost port (atgs-serve's server) for the block; yields its URL."""
    from atgs.web.server import make_server

    server = make_server(Path(folder), "127.0.0.1", 0)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/"
    finally:
        server.shutdown()
        server.server_close()


@contextmanager
def chromium() -> Iterator[object]:
    """A headless Chromium (a Playwright Browser) for the block."""
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        raise BrowserUnavailable("Playwright is not installed; run: .venv/bin/pip install playwright") from None
    exe = chromium_path()
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=exe, args=CHROMIUM_ARGS)
        try:
            yield browser
        finally:
            browser.close()


class PlayerPage:
    """One open player page. ``params``: the page's URL parameters (docs/web.md). ``touch``: a
    touch screen (touch events, pointers of type touch); ``fake_clock``: Playwright's clock drives
    the page's time (requestAnimationFrame included), so a test can step playback by exact times
    (``page.clock.run_for``) after ``page.clock.pause_at``. ``routes``: (URL pattern, handler)
    pairs of Playwright's ``page.route``, installed before the page loads (a test that fails a file
    must catch its first request, which the look-ahead may make at once)."""

    def __init__(self, browser, url: str, params: dict[str, object] | None = None, timeout_s: float = 60.0,
                 touch: bool = False, fake_clock: bool = False, routes: list | None = None):
        query = "&".join(f"{k}={v}" for k, v in (params or {}).items())
        self.page = browser.new_page(device_scale_factor=1, has_touch=touch)
        if fake_clock:
            self.page.clock.install()
        self.page.set_default_timeout(timeout_s * 1000)
        self.console: list[str] = []
        self.page.on("console", lambda m: self.console.append(f"{m.type}: {m.text}"))
        self.page.on("pageerror", lambda e: self.console.append(f"pageerror: {e}"))
        for pattern, handler in routes or ():
            self.page.route(pattern, handler)
        self.page.goto(url + "index.html" + (f"?{query}" if query else ""))

    def call(self, expression: str):
        """Evaluate ``expression`` (may await) with ``p`` bound to window.atgsPlayer."""
        self.page.wait_for_function("() => window.atgsPlayer !== undefined")
        return self.page.evaluate(f"async () => {{ const p = window.atgsPlayer; return {expression}; }}")

    def first_frame(self) -> None:
        self.call("await p.whenFirstFrame()")

    def seek(self, index: int) -> None:
        self.call(f"await p.seek({int(index)})")

    def state(self) -> dict:
        return self.call("p.state()")

    def pixels(self) -> np.ndarray:
        """(H, W, 3) float in [0, 1]: the last drawn image as the browser read it back, top row first."""
        r = self.call("p.readPixels()")
        data = r["data"]
        raw = base64.b64decode(data) if isinstance(data, str) else bytes(data)
        rgba = np.frombuffer(raw, np.uint8).reshape(r["height"], r["width"], 4)
        return rgba[..., :3].astype(np.float32) / 255.0

    def error_text(self, timeout_s: float = 30.0) -> str:
        """The page's visible error line (waits for it to appear)."""
        el = self.page.locator("#error")
        el.wait_for(state="visible", timeout=timeout_s * 1000)
        return el.inner_text()

    def close(self) -> None:
        self.page.close()
