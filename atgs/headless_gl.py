"""Headless OpenGL contexts (no window, no display) for the viewer, tests and synthetic data.

Two routes to Mesa's software rasterizer (llvmpipe):
- ``"egl"``: ``moderngl.create_standalone_context(backend="egl")`` (surfaceless EGL);
- ``"osmesa"``: libOSMesa through ctypes: ``OSMesaCreateContextAttribs`` (core profile 3.3+),
  ``OSMesaMakeCurrent`` on a small client buffer, then ``moderngl.init_context`` with a loader
  whose ``load_opengl_function`` is ``OSMesaGetProcAddress``.
- ``"auto"``: EGL first, then OSMesa.

Render into framebuffers created on the returned context (``ctx.framebuffer(...)``); the
OSMesa client buffer is only there to make the context current.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from typing import Literal

import moderngl

from atgs.errors import UserError

GLBackend = Literal["auto", "egl", "osmesa"]
MIN_GL_VERSION = 330

# OSMesa constants (GL/osmesa.h; the header is not installed with the runtime package).
_OSMESA_FORMAT = 0x22
_OSMESA_DEPTH_BITS = 0x30
_OSMESA_STENCIL_BITS = 0x31
_OSMESA_PROFILE = 0x33
_OSMESA_CORE_PROFILE = 0x34
_OSMESA_CONTEXT_MAJOR_VERSION = 0x36
_OSMESA_CONTEXT_MINOR_VERSION = 0x37
_GL_RGBA = 0x1908
_GL_UNSIGNED_BYTE = 0x1401
_OSMESA_LIBS = ("libOSMesa.so.8", "libOSMesa.so.6", "libOSMesa.so")
_BUF_SIZE = 16  # the client buffer is never drawn into; FBOs are


class HeadlessGLError(UserError, RuntimeError):
    """No usable headless OpenGL context (message is one line and names the fix)."""


class _OSMesaLoader:
    """Owns one OSMesa context; moderngl calls it to resolve GL functions and to make it current."""

    def __init__(self, lib: ctypes.CDLL, major: int, minor: int) -> None:
        self._lib = lib
        attrs = [
            _OSMESA_FORMAT, _GL_RGBA,
            _OSMESA_DEPTH_BITS, 24,
            _OSMESA_STENCIL_BITS, 8,
            _OSMESA_PROFILE, _OSMESA_CORE_PROFILE,
            _OSMESA_CONTEXT_MAJOR_VERSION, major,
            _OSMESA_CONTEXT_MINOR_VERSION, minor,
            0,
        ]
        arr = (ctypes.c_int * len(attrs))(*attrs)
        self._ctx = lib.OSMesaCreateContextAttribs(arr, None)
        if not self._ctx:
            raise HeadlessGLError(
                f"OSMesa could not create an OpenGL {major}.{minor} core context; "
                "install a recent Mesa: apt-get install libosmesa6"
            )
        self._buf = (ctypes.c_ubyte * (_BUF_SIZE * _BUF_SIZE * 4))()
        self.make_current()

    def make_current(self) -> None:
        if not self._ctx:
            raise HeadlessGLError("the OSMesa context was released")
        ok = self._lib.OSMesaMakeCurrent(self._ctx, self._buf, _GL_UNSIGNED_BYTE, _BUF_SIZE, _BUF_SIZE)
        if not ok:
            raise HeadlessGLError("OSMesaMakeCurrent failed; reinstall Mesa: apt-get install libosmesa6")

    # --- moderngl loader protocol -------------------------------------------------------------
    def load_opengl_function(self, name: str) -> int:
        return self._lib.OSMesaGetProcAddress(name.encode("ascii")) or 0

    def release(self) -> None:
        if self._ctx:
            self._lib.OSMesaDestroyContext(self._ctx)
            self._ctx = None

    def __enter__(self) -> "_OSMesaLoader":
        self.make_current()
        return self

    def __exit__(self, *exc: object) -> None:
        return None


def _load_osmesa_lib() -> ctypes.CDLL:
    names = list(_OSMESA_LIBS)
    found = ctypes.util.find_library("OSMesa")
    if found and found not in names:
        names.append(found)
    for name in names:
        try:
            lib = ctypes.CDLL(name)
        except OSError:
            continue
        lib.OSMesaCreateContextAttribs.restype = ctypes.c_void_p
        lib.OSMesaCreateContextAttribs.argtypes = [ctypes.POINTER(ctypes.c_int), ctypes.c_void_p]
        lib.OSMesaMakeCurrent.restype = ctypes.c_ubyte
        lib.OSMesaMakeCurrent.argtypes = [
            ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint, ctypes.c_int, ctypes.c_int,
        ]
        lib.OSMesaGetProcAddress.restype = ctypes.c_void_p
        lib.OSMesaGetProcAddress.argtypes = [ctypes.c_char_p]
        lib.OSMesaDestroyContext.restype = None
        lib.OSMesaDestroyContext.argtypes = [ctypes.c_void_p]
        return lib
    raise HeadlessGLError("libOSMesa not found; install it with: apt-get install libosmesa6")


def _check_version(ctx: moderngl.Context, backend: str) -> moderngl.Context:
    if ctx.version_code < MIN_GL_VERSION:
        got = ctx.info.get("GL_VERSION", str(ctx.version_code))
        ctx.release()
        raise HeadlessGLError(
            f"{backend} gives OpenGL {got}, ATGS needs 3.3 core; install a newer Mesa "
            "(apt-get install libegl-mesa0 libosmesa6)"
        )
    return ctx


def create_egl_context() -> moderngl.Context:
    try:
        ctx = moderngl.create_standalone_context(backend="egl", require=MIN_GL_VERSION)
    except Exception as exc:  # glcontext raises plain Exceptions with multi-line text
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise HeadlessGLError(
            f"EGL context failed ({first}); install Mesa EGL: apt-get install libegl1 libegl-mesa0"
        ) from exc
    return _check_version(ctx, "EGL")


def create_osmesa_context() -> moderngl.Context:
    lib = _load_osmesa_lib()
    loader = _OSMesaLoader(lib, 3, 3)
    try:
        moderngl.init_context(loader=loader)
        ctx = moderngl.get_context()
    except Exception as exc:
        loader.release()
        raise HeadlessGLError(f"moderngl could not use the OSMesa context ({exc}); apt-get install libosmesa6") from exc
    ctx.extra = {"osmesa_loader": loader}  # keeps the context and its buffer alive with ctx
    return _check_version(ctx, "OSMesa")


def create_headless_context(backend: str = "auto") -> moderngl.Context:
    """A moderngl context with OpenGL >= 3.3 core and no window.

    ``backend``: "egl", "osmesa" or "auto" (EGL, then OSMesa). Raises :class:`HeadlessGLError`
    with a one-line message naming what to install if nothing works.
    """
    if backend == "egl":
        return create_egl_context()
    if backend == "osmesa":
        return create_osmesa_context()
    if backend != "auto":
        raise HeadlessGLError(f"unknown GL backend {backend!r}; use one of: auto, egl, osmesa")
    errors: list[str] = []
    for make in (create_egl_context, create_osmesa_context):
        try:
            return make()
        except HeadlessGLError as exc:
            errors.append(str(exc))
    raise HeadlessGLError(
        "no headless OpenGL 3.3 available (" + " | ".join(errors) + "); "
        "install Mesa: apt-get install libegl-mesa0 libosmesa6"
    )


def gl_description(ctx: moderngl.Context) -> str:
    """'renderer, version' of a context, for logs and benchmark reports."""
    info = ctx.info
    return f"{info.get('GL_RENDERER', '?')}, OpenGL {info.get('GL_VERSION', '?')}"
