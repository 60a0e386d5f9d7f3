"""Headless OpenGL contexts: OSMesa (forced), EGL, auto, and clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from atgs.headless_gl import HeadlessGLError, create_headless_context, gl_description


def _clear_and_read(ctx) -> np.ndarray:
    fbo = ctx.simple_framebuffer((4, 3), components=4)
    fbo.use()
    fbo.clear(0.25, 0.5, 1.0, 1.0)
    return np.frombuffer(fbo.read(components=4), np.uint8).reshape(3, 4, 4)


@pytest.mark.parametrize("backend", ["osmesa", "egl", "auto"])
def test_context_renders_and_is_core_33_or_newer(backend: str) -> None:
    ctx = create_headless_context(backend)
    try:
        assert ctx.version_code >= 330
        assert "llvmpipe" in gl_description(ctx) or "Mesa" in gl_description(ctx)
        px = _clear_and_read(ctx)
        assert (px == np.array([64, 128, 255, 255], np.uint8)).all()
    finally:
        ctx.release()


def test_osmesa_context_can_be_recreated() -> None:
    for _ in range(2):
        ctx = create_headless_context("osmesa")
        with ctx:  # the loader makes its context current
            assert _clear_and_read(ctx)[0, 0, 2] == 255
        ctx.release()


def test_unknown_backend_is_a_one_line_error() -> None:
    with pytest.raises(HeadlessGLError) as info:
        create_headless_context("vulkan")
    msg = str(info.value)
    assert "\n" not in msg and "osmesa" in msg


def test_missing_osmesa_names_the_package(monkeypatch: pytest.MonkeyPatch) -> None:
    import atgs.headless_gl as hg

    monkeypatch.setattr(hg, "_OSMESA_LIBS", ("libOSMesa-does-not-exist.so",))
    monkeypatch.setattr(hg.ctypes.util, "find_library", lambda name: None)
    with pytest.raises(HeadlessGLError, match="apt-get install libosmesa6"):
        create_headless_context("osmesa")
