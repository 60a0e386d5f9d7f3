"""What a render target shows: display mapping of the render modes, and screenshots on disk
(atomic, through atgs.io.atomic; videos are atgs.io.video's)."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
from PIL import Image

from atgs.io.atomic import atomic_file, publish_dir, temp_dir_beside
from atgs.viewer.errors import ViewerError


def colormap(x: np.ndarray) -> np.ndarray:
    """The same blue -> cyan -> yellow -> red ramp as atgs/shaders/present.frag (x in [0, 1])."""
    x = np.clip(x, 0.0, 1.0)[..., None]
    centers = np.array([3.0, 2.0, 1.0])
    return np.clip(1.5 - np.abs(4.0 * x - centers), 0.0, 1.0)


def depth_range(raw: np.ndarray) -> tuple[float, float]:
    """(min, max) expected depth over the covered pixels of a depth-mode target."""
    a = raw[..., 3]
    covered = a > 1e-4
    if not covered.any():
        return 0.0, 1.0
    z = raw[..., 0][covered] / a[covered]
    return float(z.min()), float(z.max())


def display_rgb(raw: np.ndarray, mode: str, background: tuple[float, float, float],
                zrange: tuple[float, float] | None = None) -> np.ndarray:
    """(H,W,4) float target (premultiplied rgb or z*alpha, alpha) -> (H,W,3) float in [0,1] for
    viewing: color as is; depth colormapped over ``zrange`` (default: this image's covered
    pixels; near = red); alpha as gray."""
    if mode == "color":
        return np.clip(raw[..., :3], 0.0, 1.0)
    a = raw[..., 3]
    if mode == "alpha":
        return np.repeat(np.clip(a, 0.0, 1.0)[..., None], 3, axis=2)
    covered = a > 1e-4
    z = np.where(covered, raw[..., 0] / np.maximum(a, 1e-4), 0.0)
    lo, hi = zrange if zrange is not None else depth_range(raw)
    x = (z - lo) / max(hi - lo, 1e-6)
    rgb = colormap(1.0 - x)
    bg = np.asarray(background, dtype=np.float64)
    return np.clip(a[..., None] * rgb + (1 - a[..., None]) * bg, 0.0, 1.0)


def to_uint8(image: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(np.asarray(image, dtype=np.float32) * 255.0), 0, 255).astype(np.uint8)


def save_image(path: str | Path, rgb8: np.ndarray) -> None:
    """Write a PNG/JPEG atomically: an existing file is replaced only when complete."""
    path = Path(path)
    fmt = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG"}.get(path.suffix.lower())
    if fmt is None:
        raise ViewerError(f"--out {path}: unsupported image type {path.suffix!r}; use .png or .jpg")
    with atomic_file(path) as tmp:
        Image.fromarray(rgb8).save(tmp, format=fmt)


class FrameDirWriter:
    """Lossless frames ``00000.png``, ``00001.png``, ... in a directory, built in a temp sibling
    and renamed into place by :meth:`close`. An existing directory is replaced only if it holds
    nothing but such frames (an earlier render), never a directory with other files. Same
    interface as :class:`atgs.io.video.VideoWriter` (write, close, abort, context manager)."""

    FRAME_NAME = re.compile(r"\d{5,}\.png")

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if self.path.exists():
            if not self.path.is_dir():
                raise ViewerError(f"--out {self.path}: exists and is not a directory; give a new directory name for PNG frames")
            if any(not self.FRAME_NAME.fullmatch(p.name) for p in self.path.iterdir()):
                raise ViewerError(f"--out {self.path}: directory holds other files than rendered frames; choose a new directory")
        self._tmp = temp_dir_beside(self.path)
        self._count = 0

    def write(self, rgb8: np.ndarray) -> None:
        Image.fromarray(rgb8).save(self._tmp / f"{self._count:05d}.png")
        self._count += 1

    def close(self) -> None:
        publish_dir(self._tmp, self.path)

    def abort(self) -> None:
        shutil.rmtree(self._tmp, ignore_errors=True)

    def __enter__(self) -> "FrameDirWriter":
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def open_video_output(path: str | Path, width: int, height: int, fps: float):
    """An H.264 video file (.mp4/.mkv/.mov, atgs.io.video.VideoWriter), or lossless PNG frames
    when ``path`` has no suffix (a directory)."""
    from atgs.io.video import VideoWriter

    if Path(path).suffix == "":
        return FrameDirWriter(path)
    return VideoWriter(path, width, height, fps, codec="libx264", crf=18, pix_fmt="yuv420p", threads=0)
