"""Shared fixtures. Helpers that tests call directly live in tests/builders.py (tiny cameras,
models, checkpoints, the toy scene), tests/layouts.py (dataset layouts) and
tests/viewer_driver.py (the scripted player window)."""

from __future__ import annotations

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
