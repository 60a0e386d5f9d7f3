"""points.ply read one keyframe at a time (atgs.keyframe_cloud's interface).

A long capture's points.ply grows with its keyframes (800k keyframe and 2.4M motion points at
1,000 frames of the synthetic capture); holding them all is what made each worker's set-up grow
with the frames (docs/training.md, "Memory per worker"). :class:`PlyPointCloud` keeps only where
each keyframe's runs of rows lie in the file and reads them with ordinary reads when asked; a
file laid out otherwise is held in memory (:class:`atgs.keyframe_cloud.ArrayPointCloud`). Both give
every keyframe's points in the file's order.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from atgs.data.errors import DataError
from atgs.keyframe_cloud import ArrayPointCloud, PointCloud

# PLY scalar types -> numpy (little endian); atgs-prepare writes float x y z, uchar rgb, int keyframe
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "<i2", "int16": "<i2",
              "ushort": "<u2", "uint16": "<u2", "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
              "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8"}
_FIELDS = ("x", "y", "z", "red", "green", "blue", "keyframe")
CHUNK_ROWS = 1 << 18  # rows a pass over the file reads at once
MAX_RUNS_PER_KEYFRAME = 8  # more (a file not grouped by keyframe): held in memory instead


class PlyPointCloud(PointCloud):
    """A binary little-endian points.ply read one keyframe at a time: opening it reads the file
    once in chunks to find each keyframe's runs of rows (a file atgs-prepare wrote holds each
    keyframe's rows together: one run each), and :meth:`rows` reads those runs."""

    def __init__(self, path: Path, dtype: np.dtype, offset: int, runs: list[np.ndarray], num_keyframes: int) -> None:
        self.path, self.dtype, self.offset = path, dtype, offset
        self._runs = runs  # per keyframe: (R, 2) int64 start, stop rows
        self.num_keyframes = int(num_keyframes)

    @classmethod
    def open(cls, path: Path, num_keyframes: int) -> PointCloud:
        """The cloud of ``path`` (keyframe indices checked against ``num_keyframes``): a
        :class:`PlyPointCloud`, or the points in memory where the file is laid out otherwise
        (ASCII, other elements, rows not grouped by keyframe)."""
        path = Path(path)
        if not path.is_file():
            raise DataError(f"{path}: not found; re-run atgs-prepare")
        layout = _binary_layout(path)
        if layout is None:
            return _in_memory(path, num_keyframes)
        dtype, offset, count = layout
        if path.stat().st_size < offset + count * dtype.itemsize:
            raise DataError(f"{path}: truncated ({count} points announced); re-run atgs-prepare")
        starts, kfs = [], []
        last = None
        with open(path, "rb") as f:
            f.seek(offset)
            for first in range(0, count, CHUNK_ROWS):
                k = np.fromfile(f, dtype, min(CHUNK_ROWS, count - first))["keyframe"].astype(np.int64)
                _check_range(path, k, num_keyframes)
                change = np.flatnonzero(np.diff(k)) + 1
                if len(k) and k[0] != last:
                    change = np.concatenate([[0], change])
                starts.append(first + change)
                kfs.append(k[change])
                if len(k):
                    last = k[-1]
        starts = np.concatenate(starts) if starts else np.zeros(0, np.int64)
        kfs = np.concatenate(kfs) if kfs else np.zeros(0, np.int64)
        if len(starts) > MAX_RUNS_PER_KEYFRAME * max(1, num_keyframes):
            return _in_memory(path, num_keyframes)
        stops = np.append(starts[1:], count)
        runs = [np.stack([starts[kfs == k], stops[kfs == k]], 1) for k in range(num_keyframes)]
        return cls(path, dtype, offset, runs, num_keyframes)

    def count(self, k: int) -> int:
        r = self._runs[k]
        return int((r[:, 1] - r[:, 0]).sum())

    def rows(self, k: int) -> np.ndarray:
        parts = []
        with open(self.path, "rb") as f:
            for start, stop in self._runs[k]:
                f.seek(self.offset + int(start) * self.dtype.itemsize)
                parts.append(np.fromfile(f, self.dtype, int(stop - start)))
        return np.concatenate(parts) if parts else np.zeros(0, self.dtype)


def _binary_layout(path: Path) -> tuple[np.dtype, int, int] | None:
    """(record dtype, data offset, rows) of a binary little-endian PLY whose only element is
    ``vertex`` with the fields ATGS reads; None for anything else."""
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise DataError(f"{path}: not a PLY file; re-run atgs-prepare")
        fmt, count, fields, elements = None, None, [], 0
        for _ in range(10_000):
            line = f.readline()
            if not line:
                raise DataError(f"{path}: unreadable point cloud (no end_header); re-run atgs-prepare")
            words = line.decode("ascii", "replace").split()
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "end_header":
                break
            if words[0] == "format":
                fmt = words[1:2]
            elif words[0] == "element":
                elements += 1
                if words[1] == "vertex" and elements == 1:
                    count = int(words[2])
            elif words[0] == "property":
                if elements != 1 or words[1] == "list" or words[1] not in _PLY_TYPES:
                    return None
                fields.append((words[2], _PLY_TYPES[words[1]]))
        offset = f.tell()
    if fmt != ["binary_little_endian"] or elements != 1 or count is None or \
            not set(_FIELDS) <= {n for n, _ in fields}:
        return None
    return np.dtype(fields), offset, count


def _check_range(path: Path, keyframes: np.ndarray, num_keyframes: int) -> None:
    if len(keyframes) and (keyframes.min() < 0 or keyframes.max() >= num_keyframes):
        raise DataError(f"{path}: keyframe index out of range [0, {num_keyframes})")


def _in_memory(path: Path, num_keyframes: int) -> ArrayPointCloud:
    pts, cols, kfs = read_points_ply(path)
    _check_range(path, kfs, num_keyframes)
    return ArrayPointCloud(pts, kfs, num_keyframes, cols)


def read_points_ply(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The whole file (plyfile): (points (P, 3) float32, colours (P, 3) float32 in [0, 1],
    keyframes (P,) int64), in the file's order."""
    from plyfile import PlyData

    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: not found; re-run atgs-prepare")
    try:
        v = PlyData.read(str(path))["vertex"].data
        pts = np.stack([v["x"], v["y"], v["z"]], axis=-1).astype(np.float32)
        cols = np.stack([v["red"], v["green"], v["blue"]], axis=-1).astype(np.float32) / 255.0
        kfs = np.asarray(v["keyframe"], dtype=np.int64)
    except Exception as e:  # plyfile raises several types for truncated/odd files
        raise DataError(f"{path}: unreadable point cloud ({type(e).__name__}: {e})") from None
    return pts.reshape(-1, 3), cols.reshape(-1, 3), kfs.reshape(-1)
