"""Images and videos on disk: display mapping of render modes, atomic PNG and MP4 writers."""

from __future__ import annotations

import io
import os
import re
import shutil
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

from viewer.errors import ViewerError


def colormap(x: np.ndarray) -> np.ndarray:
    """The same blue -> cyan -> yellow -> red ramp as shaders/present.frag (x in [0, 1])."""
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


def _publish(tmp: str, path: Path) -> None:
    """Rename a finished temp file into place with ordinary permissions (mkstemp makes 0600)."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    os.replace(tmp, path)


def _check_parent(path: Path, what: str) -> None:
    if path.exists() and path.is_dir():
        raise ViewerError(f"--out {path}: is a directory; give a {what} file name")
    parent = path.parent if str(path.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)


def save_image(path: str | Path, rgb8: np.ndarray) -> None:
    """Write atomically (temp file + rename): an existing file is replaced only when complete."""
    path = Path(path)
    _check_parent(path, "PNG/JPEG")
    fmt = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG"}.get(path.suffix.lower())
    if fmt is None:
        raise ViewerError(f"--out {path}: unsupported image type {path.suffix!r}; use .png or .jpg")
    buf = io.BytesIO()
    Image.fromarray(rgb8).save(buf, format=fmt)
    write_atomic(path, buf.getvalue())


def write_atomic(path: str | Path, data: bytes) -> None:
    """Write a file through a temp file in its directory renamed into place (created if missing)."""
    path = Path(path)
    if path.is_dir():
        raise ViewerError(f"{path}: is a directory; give a file name")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".tmp-", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        _publish(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


class VideoWriter:
    """H.264 MP4 through PyAV, written to a temp file renamed into place by :meth:`close`."""

    def __init__(self, path: str | Path, width: int, height: int, fps: float, crf: int = 18) -> None:
        import av
        from fractions import Fraction

        self.path = Path(path)
        _check_parent(self.path, "video (.mp4)")
        if self.path.suffix.lower() not in (".mp4", ".mkv", ".mov"):
            raise ViewerError(f"--out {self.path}: use a .mp4, .mkv or .mov file name, or a directory name for PNG frames")
        if width % 2 or height % 2:
            raise ViewerError(f"--size {width}x{height}: H.264 needs an even width and height")
        fd, self._tmp = tempfile.mkstemp(prefix=self.path.name + ".tmp-", suffix=self.path.suffix, dir=self.path.parent)
        os.close(fd)
        self._container = av.open(self._tmp, mode="w")
        rate = Fraction(fps).limit_denominator(1001)
        self._stream = self._container.add_stream("libx264", rate=rate)
        self._stream.width, self._stream.height = width, height
        self._stream.pix_fmt = "yuv420p"
        self._stream.options = {"crf": str(crf), "preset": "veryfast"}
        self._done = False

    def write(self, rgb8: np.ndarray) -> None:
        import av

        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb8), format="rgb24")
        for packet in self._stream.encode(frame):
            self._container.mux(packet)

    def close(self) -> None:
        for packet in self._stream.encode():
            self._container.mux(packet)
        self._container.close()
        _publish(self._tmp, self.path)
        self._done = True

    def abort(self) -> None:
        try:
            self._container.close()
        finally:
            if os.path.exists(self._tmp):
                os.unlink(self._tmp)


class FrameDirWriter:
    """Lossless frames ``00000.png``, ``00001.png``, ... in a directory, built in a temp sibling
    and renamed into place by :meth:`close`. An existing directory is replaced only if it holds
    nothing but such frames (an earlier render), never a directory with other files."""

    FRAME_NAME = re.compile(r"\d{5,}\.png")

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if self.path.exists():
            if not self.path.is_dir():
                raise ViewerError(f"--out {self.path}: exists and is not a directory; give a new directory name for PNG frames")
            if any(not self.FRAME_NAME.fullmatch(p.name) for p in self.path.iterdir()):
                raise ViewerError(f"--out {self.path}: directory holds other files than rendered frames; choose a new directory")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = Path(tempfile.mkdtemp(prefix=self.path.name + ".tmp-", dir=self.path.parent))
        self._count = 0

    def write(self, rgb8: np.ndarray) -> None:
        Image.fromarray(rgb8).save(self._tmp / f"{self._count:05d}.png")
        self._count += 1

    def close(self) -> None:
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(self._tmp, 0o777 & ~umask)  # mkdtemp makes 0700
        old = None
        if self.path.exists():
            old = Path(tempfile.mkdtemp(prefix=self.path.name + ".old-", dir=self.path.parent))
            os.rmdir(old)
            os.replace(self.path, old)
        os.replace(self._tmp, self.path)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)

    def abort(self) -> None:
        shutil.rmtree(self._tmp, ignore_errors=True)


def open_video_output(path: str | Path, width: int, height: int, fps: float) -> "VideoWriter | FrameDirWriter":
    """A video file (.mp4/.mkv/.mov), or PNG frames when ``path`` has no suffix (a directory)."""
    return FrameDirWriter(path) if Path(path).suffix == "" else VideoWriter(path, width, height, fps)
