"""GLSL shaders (splatting, present, compute: decode and depth sort), shipped as package data."""

from __future__ import annotations

from importlib.resources import files


def load_shader(name: str, defines: dict[str, int] | None = None) -> str:
    """Shader source; ``defines`` become ``#define`` lines right after the ``#version`` line."""
    text = files("atgs.shaders").joinpath(name).read_text(encoding="utf-8")
    if not defines:
        return text
    version, rest = text.split("\n", 1)
    return "\n".join([version, *(f"#define {k} {v}" for k, v in defines.items()), rest])
