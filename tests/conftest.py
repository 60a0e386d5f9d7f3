"""Shared fixtures. Helpers that tests call directly live in tests/builders.py (tiny cameras,
models, checkpoints, the toy scene), tests/layouts.py (dataset layouts) and
tests/viewer_driver.py (the scripted player window)."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="module")
def renderer():
    """A headless (OSMesa) splat renderer, one per test module."""
    from atgs.headless_gl import create_headless_context
    from atgs.viewer.splat_renderer import SplatRenderer

    ctx = create_headless_context("osmesa")
    r = SplatRenderer(ctx)
    yield r
    r.release()
    ctx.release()


@pytest.fixture(scope="session")
def toy_scene_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """builders.make_toy_scene written as a prepared scene (atgs-prepare's output) for the CLIs."""
    from atgs.data.scene import write_prepared_scene
    from builders import make_toy_scene

    s = make_toy_scene(num_frames=6, num_cameras=4, width=32, height=24, keyframes=3)
    out = tmp_path_factory.mktemp("scene") / "toy"
    write_prepared_scene(out, s)  # colours: grey
    return out


@pytest.fixture(scope="module")
def compute_ctx():
    """A headless GL context with compute shaders (OpenGL 4.3: the GL decode and sort), one per
    test module. Mesa's llvmpipe gives 4.5 (scripts/setup.sh installs it); without it the tests
    fail with the fix rather than skip, since the feature would go untested."""
    from atgs.headless_gl import create_headless_context

    ctx = create_headless_context("auto")  # (no GL at all: HeadlessGLError names the package)
    if ctx.version_code < 430:
        ctx.release()
        pytest.fail(f"OpenGL {ctx.version_code // 100}.{ctx.version_code % 100 // 10} has no compute shaders; "
                    "the GL decode and sort need 4.3: install Mesa 20 or newer (apt-get install libegl-mesa0)")
    yield ctx
    ctx.release()
