"""Video input through PyAV (FFmpeg). Frames stream one at a time; nothing is buffered.
Writing videos is :mod:`atgs.io.video`'s job."""

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


# Below this many frames, decoding forward costs about as much as a seek does.
SEEK_MIN_FRAMES = 32
# Packets read past the wanted frame when ranking timestamps (covers B-frame reordering).
_REORDER_MARGIN = 64


def _presentation_pts(c, stream, count: int) -> list[int] | None:
    """Timestamps of the first ``count`` frames in presentation (= decoding output) order, from
    the packets alone (demuxing reads the file but decodes nothing); None without timestamps."""
    pts = []
    for pkt in c.demux(stream):
        if not pkt.size:
            continue
        if pkt.pts is None:
            return None
        pts.append(int(pkt.pts))
        if len(pts) >= count + _REORDER_MARGIN:
            break
    return sorted(pts)[:count]


def _frames_after_seek(c, path: Path, start: int) -> Iterator[tuple[int, object]] | None:
    """Seek to the keyframe at or before frame ``start`` and yield (index, frame) from there, or
    return None when that cannot be done exactly (no timestamps, a short file, frames that do not
    match the packets' timestamps). A frame's index is the rank of its timestamp among the
    packets', i.e. its position in decoding order, the same as without seeking; it holds for
    variable frame rates too."""
    s = c.streams.video[0]
    try:
        order = _presentation_pts(c, s, start + 1)
        if order is None or len(order) <= start or len(set(order)) != len(order):
            return None
        rank = {p: i for i, p in enumerate(order)}
        c.seek(order[start], backward=True, any_frame=False, stream=s)
        frames = _decode(c, path)
        ahead = []
        for frame in frames:  # from the keyframe up to `start`: every timestamp must be the next one
            i = rank.get(frame.pts) if not ahead else ahead[-1][0] + 1
            if i is None or i > start or order[i] != frame.pts:
                return None
            ahead.append((i, frame))
            if i == start:
                break
    except Exception:  # noqa: BLE001 - a failed seek or decode: decode from the start instead
        return None
    if not ahead or ahead[-1][0] != start:
        return None

    def run() -> Iterator[tuple[int, object]]:
        yield from ahead
        yield from enumerate(frames, start=start + 1)

    return run()


def iter_frames(path: Path, start: int = 0, end: int | None = None, step: int = 1) -> Iterator[tuple[int, np.ndarray]]:
    """Yield (frame index, (H,W,3) uint8 RGB) for frames start, start+step, ... < end.

    Frame i is the i-th frame in decoding order. A far ``start`` (>= SEEK_MIN_FRAMES) seeks to
    the keyframe before it instead of decoding every earlier frame, when the file's timestamps
    agree with that order (checked on the frames decoded up to ``start``); otherwise it decodes
    from the beginning."""
    path = Path(path)
    seeked = None
    if start >= SEEK_MIN_FRAMES:
        c = _open(path)
        seeked = _frames_after_seek(c, path, start)
        if seeked is None:
            c.close()
    if seeked is None:
        c = _open(path)
        seeked = enumerate(_decode(c, path))
    with c:
        for i, frame in seeked:
            if end is not None and i >= end:
                break
            if i >= start and (i - start) % step == 0:
                yield i, frame.to_ndarray(format="rgb24")
