"""The one video encoder (PyAV / FFmpeg), streaming and atomic.

Frames are encoded one at a time into a temporary file beside the output, which :meth:`close`
renames into place: an interrupted or failed run never leaves a partial video, and an existing
file is replaced only by a complete one. Reading videos is :mod:`atgs.data.video`'s job.
"""

from __future__ import annotations

import os
import tempfile
from fractions import Fraction
from pathlib import Path

import numpy as np

from atgs.errors import OutputError
from atgs.io.atomic import publish

VIDEO_SUFFIXES = (".mp4", ".mkv", ".mov")
# chroma-subsampled pixel formats need even frame sizes
_EVEN_SIZE_FORMATS = ("yuv420p", "yuv422p", "nv12")


class VideoWriter:
    """Streaming encoder. Default ``libx264rgb`` with crf 0 is lossless RGB (exact ground truth
    of the synthetic scenes); ``libx264`` + ``yuv420p`` gives the usual lossy, widely playable
    files (``atgs-render``). Use as a context manager, or call :meth:`close` (publish) or
    :meth:`abort` (discard)."""

    def __init__(self, path: str | Path, width: int, height: int, fps: float, codec: str = "libx264rgb",
                 crf: int = 0, pix_fmt: str | None = None, preset: str = "veryfast", threads: int = 1) -> None:
        import av

        self.path = Path(path)
        if self.path.suffix.lower() not in VIDEO_SUFFIXES:
            raise OutputError(f"{self.path}: use a {', '.join(VIDEO_SUFFIXES)} file name for a video")
        if self.path.is_dir():
            raise OutputError(f"{self.path}: is a directory; give a video file name")
        pix_fmt = pix_fmt or ("rgb24" if codec == "libx264rgb" else "yuv444p")
        if pix_fmt in _EVEN_SIZE_FORMATS and (width % 2 or height % 2):
            raise OutputError(f"{self.path}: {width}x{height} is odd; {pix_fmt} video needs an even width and height")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=self.path.name + ".tmp-", suffix=self.path.suffix, dir=self.path.parent)
        os.close(fd)
        self._tmp = Path(tmp)
        self.container = av.open(str(self._tmp), mode="w")
        self.stream = self.container.add_stream(codec, rate=Fraction(fps).limit_denominator(1001))
        self.stream.width, self.stream.height = int(width), int(height)
        self.stream.pix_fmt = pix_fmt
        if codec.startswith("libx264"):
            self.stream.options = {"crf": str(int(crf)), "preset": preset}
        self.stream.thread_count = threads  # 1: several writers run side by side (atgs-synth); 0 = auto
        self.frames = 0
        self._open = True

    def write(self, rgb: np.ndarray) -> None:
        import av

        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb[..., :3], dtype=np.uint8), format="rgb24")
        for packet in self.stream.encode(frame):
            self.container.mux(packet)
        self.frames += 1

    def close(self) -> None:
        """Flush the encoder and publish the file."""
        if not self._open:
            return
        try:
            for packet in self.stream.encode():
                self.container.mux(packet)
            self.container.close()
            self._open = False
            publish(self._tmp, self.path)
        except BaseException:
            self.abort()
            raise

    def abort(self) -> None:
        """Discard the partial video; ``path`` stays as it was."""
        self._open = False
        try:
            self.container.close()
        except Exception:  # noqa: BLE001 - closing a half-written container may fail; it is deleted anyway
            pass
        finally:
            if self._tmp.exists():
                self._tmp.unlink()

    def __enter__(self) -> "VideoWriter":
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
