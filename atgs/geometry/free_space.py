"""Space the images prove empty: in front of the measured points each camera sees.

A point measured on a surface and seen by a camera shows that the segment between the camera
and the point is empty. Each camera keeps, per cell of a coarse grid over its image, the depth of
the nearest point in the cell; a position lying in front of that depth (closer than ``margin``
times it) in any camera is in empty space. Cells without points say nothing, so unseen and
unmeasured space is never called empty. The grid is coarse (GRID_CELLS along the long side) so
that the gaps between measured points do not read as holes through a surface.

One owner for three users: the random static anchors (atgs.model.random_anchors) and the fill of
atgs-prepare (atgs.data.keyframe_points) are kept out of it, and training's free-space loss
(atgs.train.losses.free_space_loss) makes the Gaussians that stand in it transparent.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from atgs.cameras import Camera
from atgs.geometry.projection import project

GRID_CELLS = 32  # cells along each image's long side
MARGIN = 0.8  # a position at depth < MARGIN x the cell's nearest point depth is in empty space


def points_in_cells(cam: Camera, points: np.ndarray, cells: int) -> tuple[np.ndarray, np.ndarray, tuple[int, int], float]:
    """The points in front of ``cam`` and inside its image: their flat cell index and depth, on a
    grid of ``cells`` cells along the image's long side; the grid's (rows, cols) and cell size
    in pixels."""
    cell = max(cam.width, cam.height) / cells
    shape = int(np.ceil(cam.height / cell)), int(np.ceil(cam.width / cell))
    if not len(points):
        return np.zeros(0, np.int64), np.zeros(0), shape, cell
    u, v, z, ok = project(cam, points)
    idx = (v[ok] // cell).astype(np.int64) * shape[1] + (u[ok] // cell).astype(np.int64)
    return idx, z[ok], shape, cell


def nearest_depth_grid(cam: Camera, points: np.ndarray, cells: int = GRID_CELLS) -> tuple[np.ndarray, float]:
    """(rows, cols) grid of the nearest point depth per image cell of ``cam`` (inf: no point),
    and the cell size in pixels."""
    idx, z, shape, cell = points_in_cells(cam, points, cells)
    grid = np.full(shape[0] * shape[1], np.inf)
    np.minimum.at(grid, idx, z)
    return grid.reshape(shape), cell


@dataclass
class FreeSpace:
    """The nearest-depth grids of a set of cameras, as tensors, for testing many positions."""

    cameras: list[Camera]
    grids: list[torch.Tensor]  # (rows, cols) float32, inf where no point
    cells: list[float]  # cell size in pixels, per camera
    margin: float = MARGIN

    @classmethod
    def of(cls, cameras: Sequence[Camera], points: np.ndarray, margin: float = MARGIN, cells: int = GRID_CELLS,
           device: torch.device | str = "cpu") -> "FreeSpace":
        return cls.of_grids(cameras, depth_grids(cameras, points, cells), margin, cells, device)

    @classmethod
    def of_parts(cls, cameras: Sequence[Camera], parts: Iterable[np.ndarray],
                 device: torch.device | str = "cpu") -> "FreeSpace":
        """From points given in parts (a keyframe's at a time): the :func:`merged_grids` of
        each part's :func:`depth_grids`, so only one part's points are held at once."""
        grids = depth_grids(cameras, np.zeros((0, 3)))  # inf: no point yet
        for pts in parts:
            grids = merged_grids(grids, depth_grids(cameras, pts))
        return cls.of_grids(cameras, grids, device=device)

    @classmethod
    def of_grids(cls, cameras: Sequence[Camera], grids: list[np.ndarray], margin: float = MARGIN,
                 cells: int = GRID_CELLS, device: torch.device | str = "cpu") -> "FreeSpace":
        """From :func:`depth_grids` (of all the points, or the elementwise minimum of those of
        parts of them: a scene's keyframes one at a time)."""
        sizes = [max(c.width, c.height) / cells for c in cameras]
        return cls(list(cameras), [torch.as_tensor(g, dtype=torch.float32, device=device) for g in grids],
                   sizes, margin)

    def kept(self, samples: np.ndarray) -> np.ndarray:
        """(N,) bool: the samples seen by at least one camera and in front of no camera's points."""
        if len(samples) == 0:
            return np.zeros(0, bool)
        empty, seen = self.test(torch.as_tensor(np.asarray(samples, np.float64)))
        return (seen & ~empty).numpy()

    def test(self, X: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(empty, seen): (N,) bool masks of the positions X (N, 3) in empty space, and of those
        inside at least one camera's image in front of it."""
        empty = torch.zeros(X.shape[0], dtype=torch.bool, device=X.device)
        seen = torch.zeros_like(empty)
        for cam, grid, cell in zip(self.cameras, self.grids, self.cells):
            u, v, z, inside = project(cam, X)
            r = (v / cell).long().clamp(0, grid.shape[0] - 1)
            c = (u / cell).long().clamp(0, grid.shape[1] - 1)
            nearest = grid[r, c].to(X.dtype)
            empty |= inside & torch.isfinite(nearest) & (z < self.margin * nearest)  # no point: nothing carved
            seen |= inside
        return empty, seen


def depth_grids(cameras: Sequence[Camera], points: np.ndarray, cells: int = GRID_CELLS) -> list[np.ndarray]:
    """Each camera's :func:`nearest_depth_grid` of ``points``."""
    return [nearest_depth_grid(c, points, cells)[0] for c in cameras]


def merged_grids(a: list[np.ndarray], b: list[np.ndarray]) -> list[np.ndarray]:
    """The nearest-depth grids of two sets of points from those of each (per camera, the
    elementwise minimum: exact and commutative, so parts folded in any order, or by several
    workers, give the grids of all the points at once)."""
    return [np.minimum(x, y) for x, y in zip(a, b)]


def carve(samples: np.ndarray, points: np.ndarray, cameras: Sequence[Camera], margin: float = MARGIN,
          cells: int = GRID_CELLS) -> np.ndarray:
    """(N,) bool: the samples seen by at least one camera and in front of no camera's points."""
    return FreeSpace.of(cameras, points, margin, cells).kept(samples)
