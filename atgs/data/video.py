"""Video input/output through PyAV (FFmpeg). Frames stream one at a time; nothing is buffered."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from atgs.data.errors import DataError

VIDEO_EXTS = (".mp4", ".mov", ".mkv", ".avi", ".webm", ".m4v")


def _open(path: Path):
    import av

    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: video not found")
    try:
        container = av.open(str(path))
    except (av.error.FFmpegError, OSError, ValueError) as e:
        raise DataError(f"{path}: cannot open video ({_short(e)}); the file is corrupt or not a video") from None
    if not container.streams.video:
        container.close()
        raise DataError(f"{path}: contains no video stream")
    return container


def _short(e: Exception) -> str:
    return str(e).strip().splitlines()[0][:160] if str(e).strip() else type(e).__name__


def video_info(path: Path, exact: bool = False) -> tuple[int, int, int, float]:
    """(num_frames, width, height, fps). ``exact`` decodes every frame to count them (slow but
    immune to wrong container headers); otherwise the container's frame count is used and
    counted by demuxing packets when the header has none."""
    path = Path(path)
    with _open(path) as c:
        s = c.streams.video[0]
        w, h = s.codec_context.width, s.codec_context.height
        fps = float(s.average_rate or s.guessed_rate or 30)
        if exact:
            n = sum(1 for _ in _decode(c, path))
        else:
            n = int(s.frames or 0)
            if n <= 0:
                try:
                    n = sum(1 for p in c.demux(s) if p.size)
                except Exception as e:  # noqa: BLE001 - any FFmpeg failure means a broken file
                    raise DataError(f"{path}: unreadable video ({_short(e)})") from None
    if n <= 0 or w <= 0 or h <= 0:
        raise DataError(f"{path}: video has no decodable frames")
    return n, w, h, fps


def _decode(container, path: Path):
    import av

    s = container.streams.video[0]
    s.thread_type = "AUTO"
    try:
        yield from container.decode(s)
    except (av.error.FFmpegError, ValueError) as e:
        raise DataError(f"{path}: video decoding failed ({_short(e)}); the file is corrupt or truncated") from None


def iter_frames(path: Path, start: int = 0, end: int | None = None, step: int = 1) -> Iterator[tuple[int, np.ndarray]]:
    """Yield (frame index, (H,W,3) uint8 RGB) for frames start, start+step, ... < end."""
    path = Path(path)
    with _open(path) as c:
        for i, frame in enumerate(_decode(c, path)):
            if end is not None and i >= end:
                break
            if i >= start and (i - start) % step == 0:
                yield i, frame.to_ndarray(format="rgb24")


def read_frame(path: Path, index: int) -> np.ndarray:
    for i, img in iter_frames(path, index, index + 1):
        return img
    raise DataError(f"{path}: has no frame {index}")


class VideoWriter:
    """Streaming encoder. Default ``libx264rgb`` with crf 0 is lossless RGB (exact ground truth);
    ``libx264`` + ``yuv444p``/``yuv420p`` gives the usual lossy files."""

    def __init__(self, path: Path, width: int, height: int, fps: float, codec: str = "libx264rgb",
                 crf: int = 0, pix_fmt: str | None = None, preset: str = "veryfast") -> None:
        import av
        from fractions import Fraction

        self.path = Path(path)
        self.container = av.open(str(self.path), mode="w")
        rate = Fraction(fps).limit_denominator(1001)
        self.stream = self.container.add_stream(codec, rate=rate)
        self.stream.width, self.stream.height = int(width), int(height)
        self.stream.pix_fmt = pix_fmt or ("rgb24" if codec == "libx264rgb" else "yuv444p")
        if codec.startswith("libx264"):
            self.stream.options = {"crf": str(int(crf)), "preset": preset}
        self.stream.thread_count = 1  # several writers run side by side; 1 thread each
        self.frames = 0

    def write(self, rgb: np.ndarray) -> None:
        import av

        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb[..., :3], dtype=np.uint8), format="rgb24")
        for packet in self.stream.encode(frame):
            self.container.mux(packet)
        self.frames += 1

    def close(self) -> None:
        for packet in self.stream.encode():
            self.container.mux(packet)
        self.container.close()

    def __enter__(self) -> "VideoWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
