"""Rendering without a window: one frame to an image, or a camera path to a video."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from atgs.cameras import Camera
from atgs.headless_gl import create_headless_context
from atgs.model.near_plane import near_of
from atgs.viewer.decode_cache import DecodeCache
from atgs.viewer.errors import ViewerError
from atgs.viewer.output import depth_range, display_rgb, to_uint8
from atgs.viewer.packing import PackedGaussians
from atgs.viewer.source import GaussianSource, decode_frame
from atgs.viewer.splat_renderer import RenderSettings, SplatRenderer


@dataclass
class HeadlessRenderer:
    """A headless GL context with a splat renderer; decode a frame, render a camera."""

    source: GaussianSource
    gl: str = "auto"
    device: torch.device | str = "cpu"  # where frames are packed and sorted (viewer.device)
    decode: str = "torch"  # or "gl": decoded and sorted in compute shaders (viewer.gl_decode)

    def __post_init__(self) -> None:
        self.ctx = create_headless_context(self.gl)
        self.renderer = SplatRenderer(self.ctx, near=near_of(self.source))  # the model's near plane
        self._frame = -1
        self.gl_decoder = None
        if self.decode == "gl":
            from atgs.viewer.gl_decode import gl_decoder_for

            try:
                self.gl_decoder = gl_decoder_for(self.ctx, self.source)
            except ViewerError:
                self.close()
                raise

    def set_frame(self, packed: PackedGaussians) -> None:
        if packed.frame != self._frame or packed.frame < 0:
            self.renderer.set_gaussians(packed)
            self._frame = packed.frame

    def render_rgb8(self, camera: Camera, settings: RenderSettings,
                    zrange: tuple[float, float] | None = None) -> np.ndarray:
        """(H,W,3) uint8 display image of the current frame (depth/alpha mapped for viewing)."""
        self.renderer.render(camera, settings)
        return to_uint8(display_rgb(self.renderer.read(), settings.mode, settings.background, zrange))

    def show_frame(self, frame: int) -> None:
        """Decode frame ``frame`` (unless it is the current one) and make it the one drawn."""
        if self.gl_decoder is None:
            self.set_frame(decode_frame(self.source, frame, self.device))
        elif frame != self._frame:
            self.renderer.set_gl_frame(self.gl_decoder.decode(frame))
            self._frame = frame

    def frame_rgb8(self, frame: int, camera: Camera, settings: RenderSettings) -> np.ndarray:
        self.show_frame(frame)
        return self.render_rgb8(camera, settings)

    def close(self) -> None:
        if self.gl_decoder is not None:
            self.gl_decoder.release()
        self.renderer.release()
        self.ctx.release()


def render_sequence(
    hr: HeadlessRenderer,
    frames: Sequence[int],
    cameras: Sequence[Camera],
    settings: RenderSettings,
    on_image,
    progress=None,
) -> dict[str, float]:
    """Render (frame[i], camera[i]) pairs, decoding ahead in a background thread; calls
    ``on_image(i, rgb8)``. Returns mean stage times in ms."""
    totals = {"decode_wait_ms": 0.0, "sort_ms": 0.0, "draw_ms": 0.0, "upload_ms": 0.0}
    zrange: tuple[float, float] | None = None
    # torch: a decode thread works ahead; gl: the decode is a dispatch the GL runs in order
    cache = DecodeCache(lambda f: decode_frame(hr.source, f, hr.device), capacity=4) if hr.gl_decoder is None else None
    with cache or contextlib.nullcontext():
        for i, (f, cam) in enumerate(zip(frames, cameras)):
            t0 = time.perf_counter()
            if cache is not None:
                cache.request(list(dict.fromkeys(frames[i : i + 3])))
                packed = cache.wait_for(f)
                assert packed is not None
                hr.set_frame(packed)
            else:
                hr.show_frame(f)
            totals["decode_wait_ms"] += (time.perf_counter() - t0) * 1e3
            if settings.mode == "depth" and zrange is None:
                hr.renderer.render(cam, settings)
                zrange = depth_range(hr.renderer.read())  # one colormap range for the whole video
            on_image(i, hr.render_rgb8(cam, settings, zrange))
            tm = hr.renderer.timings
            totals["sort_ms"] += tm.sort_ms
            totals["draw_ms"] += tm.draw_ms
            totals["upload_ms"] += tm.upload_ms if tm.sorted_again else 0.0
            if progress is not None:
                progress.update(1)
    n = max(1, len(frames))
    return {k: v / n for k, v in totals.items()}
