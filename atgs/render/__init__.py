"""Differentiable Gaussian rasterizer: ``rasterize(...) -> RasterOutput``.

Backends: "cpu" (compiled C++/OpenMP, tile-based, hand-written backward), "torch" (slow dense
reference used by the tests), "cuda" (thin gsplat wrapper; its tests need a GPU). See docs/rasterizer.md.
"""

from atgs.render.api import BACKENDS, rasterize, rasterize_gaussians, warm_up
from atgs.render.types import RasterOutput
from atgs.render.validate import RasterInputError

__all__ = ["BACKENDS", "RasterInputError", "RasterOutput", "rasterize", "rasterize_gaussians", "warm_up"]
