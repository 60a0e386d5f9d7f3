"""A scene's points grouped by keyframe, read one keyframe at a time (the interface the model's
set-up reads, atgs.model.anchor_setup): :class:`PointCloud`, and :class:`ArrayPointCloud` over
arrays in memory. atgs.data.point_cloud reads a points.ply file through it, one keyframe's rows at
a time, so a long capture's points are never all held (docs/training.md, "Memory per worker")."""

from __future__ import annotations

import numpy as np


class PointCloud:
    """Points grouped by keyframe index (0 .. ``num_keyframes`` - 1)."""

    num_keyframes: int

    def count(self, k: int) -> int:
        raise NotImplementedError

    def rows(self, k: int) -> np.ndarray:
        """Keyframe ``k``'s records (a structured array with the fields x y z red green blue)."""
        raise NotImplementedError

    def read(self, k: int) -> np.ndarray:
        """(n, 3) float32: keyframe ``k``'s points."""
        return _xyz(self.rows(k))

    def read_with_colors(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Keyframe ``k``'s points (n, 3) float32 and their colours (n, 3) float32 in [0, 1], from
        one read of its rows."""
        recs = self.rows(k)
        return _xyz(recs), _rgb(recs)

    def __len__(self) -> int:
        return sum(self.count(k) for k in range(self.num_keyframes))

    def whole(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every point in keyframe order: (points (P, 3) float32, colours (P, 3) float32 in [0, 1],
        keyframes (P,) int64)."""
        parts = [self.rows(k) for k in range(self.num_keyframes)]
        recs = np.concatenate(parts) if parts else np.zeros(0, _record_dtype())
        kfs = np.concatenate([np.full(len(r), k, np.int64) for k, r in enumerate(parts)]) if parts else \
            np.zeros(0, np.int64)
        return _xyz(recs), _rgb(recs), kfs

    def measured_mask(self, measured: list[int] | None) -> np.ndarray:
        """(P,) bool over :meth:`whole`'s order: each keyframe k's first ``measured[k]`` points
        (all where None)."""
        counts = [self.count(k) for k in range(self.num_keyframes)]
        if measured is None:
            return np.ones(sum(counts), bool)
        return np.concatenate([np.arange(n) < m for n, m in zip(counts, measured)] or [np.zeros(0, bool)])


def _record_dtype() -> np.dtype:
    return np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])


def _xyz(recs: np.ndarray) -> np.ndarray:
    return np.stack([recs["x"], recs["y"], recs["z"]], -1).astype(np.float32).reshape(-1, 3)


def _rgb(recs: np.ndarray) -> np.ndarray:
    return np.stack([recs["red"], recs["green"], recs["blue"]], -1).astype(np.float32).reshape(-1, 3) / 255.0


class ArrayPointCloud(PointCloud):
    """Points held in memory, grouped by ``keyframes`` (colours: grey when None)."""

    def __init__(self, points: np.ndarray, keyframes: np.ndarray, num_keyframes: int,
                 colors: np.ndarray | None = None) -> None:
        points = np.asarray(points, np.float32).reshape(-1, 3)
        keyframes = np.asarray(keyframes, np.int64).reshape(-1)
        recs = np.zeros(len(points), _record_dtype())
        recs["x"], recs["y"], recs["z"] = points.T
        c = np.full((len(points), 3), 128, np.uint8) if colors is None else np.clip(
            np.round(np.asarray(colors, np.float64).reshape(-1, 3) * 255.0), 0, 255).astype(np.uint8)
        recs["red"], recs["green"], recs["blue"] = c.T
        order = np.argsort(keyframes, kind="stable")
        self._recs = recs[order]
        self._starts = np.searchsorted(keyframes[order], np.arange(num_keyframes + 1))
        self.num_keyframes = int(num_keyframes)

    def count(self, k: int) -> int:
        return int(self._starts[k + 1] - self._starts[k])

    def rows(self, k: int) -> np.ndarray:
        return self._recs[self._starts[k]:self._starts[k + 1]]
