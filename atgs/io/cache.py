"""Where ATGS keeps what it can rebuild: the compiled rasterizer and the built-in synthetic scene.

One root for every cache: ``$ATGS_CACHE_DIR`` if set, else ``$XDG_CACHE_HOME/atgs``, else
``~/.cache/atgs``.
"""

from __future__ import annotations

import os
from pathlib import Path


def cache_dir() -> Path:
    """The root of every ATGS cache (read from the environment on each call)."""
    base = os.environ.get("ATGS_CACHE_DIR")
    if base:
        return Path(base)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "atgs"
