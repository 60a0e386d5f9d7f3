"""Wait for the GL without holding Python's GIL.

moderngl's ``ctx.finish()`` (and any moderngl call that has to wait for llvmpipe) keeps the GIL
for the whole ~100 ms splat draw, so the decode thread cannot run its Python glue between
torch ops: streaming playback then showed 2 distinct frames out of 40. A glFinish called
through ctypes releases the GIL while it waits. libOpenGL (libglvnd) dispatches it to the
context current on this thread, whether it was made by GLX (the glfw window) or EGL (headless).
"""

from __future__ import annotations

import ctypes
from collections.abc import Callable

_GL_LIBS = ("libOpenGL.so.0", "libGL.so.1")


def gil_free_finish(fallback: Callable[[], None]) -> Callable[[], None]:
    """A ``glFinish()`` that releases the GIL; ``fallback`` (e.g. ``ctx.finish``) if no
    libglvnd GL library is found (then waiting still works, only with the GIL held)."""
    for name in _GL_LIBS:
        try:
            fn = ctypes.CDLL(name).glFinish
        except (OSError, AttributeError):
            continue
        fn.restype, fn.argtypes = None, []
        return fn
    return fallback
