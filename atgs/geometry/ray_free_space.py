"""Space a training camera sees through, judged per ray: the measured depth of each pixel.

A keyframe point that a training camera sees at its keyframe's frame proves that the camera's
ray to it passes through empty space up to it. Each training camera keeps, per small cell of
its image (``CELL_PX`` pixels at the training resolution), the depth of the nearest such point:

- ``at_frame[f]``: that of the points measured at frame ``f`` (a keyframe or a motion
  keyframe). At such a frame every Gaussian is judged against it where it measured the ray: a
  static anchor's Gaussians change with time too, and a ghost of a walking person left where
  she stood at another moment is as wrong as fog;
- ``static``: the nearest over every measured frame. Space in front of it was empty at every
  measured moment, so at any other frame a Gaussian of an always-active (static) anchor there is
  wrong; a Gaussian of a moving (per-keyframe) anchor is judged only at measured frames, since
  between them something may move through a ray that was empty at both.

Only points the camera itself sees count: a point measured by other cameras behind a surface
that this camera sees would claim this camera's ray empty through the surface. A point is taken
as seen when the camera's pixel at it (3x3 neighbourhood) has the point's colour within
``VISIBLE_TOLERANCE``; an occluder rarely has the colour of what it hides. A cell's depth is the
median of its points' depths, not the nearest: stereo on a uniform wall leaves a few wrong
points in the air in front of it, grey like the wall, which no colour test catches; the nearest
would let each of them shield the fog that training builds around it. Cells are then
min-filtered over their measured 3x3 neighbours so that depth edges keep the nearer side.
Unmeasured cells say nothing.

The training loss (:func:`atgs.train.losses.ray_free_space_loss`) renders, from a training
view, the Gaussians standing in front of their pixel's measured depth, and pushes down the
opacity they accumulate on the rays whose measured depth lies behind them. That is what makes a
semi-transparent fog in front of a uniform wall, cheap for the training views, go.

Owner of the per-ray test; :mod:`atgs.geometry.free_space` is the coarse per-position test of the
set-up (random anchors, atgs-prepare's fill).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from atgs.cameras import Camera
from atgs.geometry.free_space import MARGIN, points_in_cells
from atgs.geometry.projection import project

CELL_PX = 4  # cell size in training pixels: a pixel's measured depth is its cell's
VISIBLE_TOLERANCE = 0.2  # mean absolute RGB difference (0..1) under which a camera sees a point


def visible_points(cam: Camera, points: np.ndarray, colors: np.ndarray, image: np.ndarray,
                   tolerance: float = VISIBLE_TOLERANCE) -> np.ndarray:
    """(P,) bool: the points in front of ``cam`` and inside its image whose colour (P, 3) in
    [0, 1] the image (H, W, 3) uint8 shows at their pixel or one of its 8 neighbours."""
    u, v, z, ok = project(cam, points)
    seen = np.zeros(len(z), bool)
    if not ok.any():
        return seen
    H, W = image.shape[:2]
    px = np.clip((u[ok] * W / cam.width).astype(np.int64), 0, W - 1)
    py = np.clip((v[ok] * H / cam.height).astype(np.int64), 0, H - 1)
    img = image.astype(np.float32) / 255.0
    col = np.asarray(colors, np.float32).reshape(-1, 3)[ok]
    best = np.full(len(px), np.inf, np.float32)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            pix = img[np.clip(py + dy, 0, H - 1), np.clip(px + dx, 0, W - 1)]
            best = np.minimum(best, np.abs(pix - col).mean(axis=1))
    seen[ok] = best <= tolerance
    return seen


def _min_filtered(grid: np.ndarray) -> np.ndarray:
    """3x3 minimum of a depth grid over its measured cells (inf: no point): a depth edge keeps
    its nearer side; an unmeasured cell stays unmeasured (a textureless occluder with no point
    of its own must not inherit the depth of what it hides)."""
    t = torch.as_tensor(grid, dtype=torch.float32)[None, None]
    low = (-F.max_pool2d(-t, 3, stride=1, padding=1))[0, 0].numpy()
    return np.where(np.isfinite(grid), low, np.inf)


def cells_of(cam: Camera, cell_px: float) -> int:
    """Cells along ``cam``'s long side for cells of about ``cell_px`` pixels."""
    return max(1, int(np.ceil(max(cam.width, cam.height) / cell_px)))


def median_depth_grid(cam: Camera, points: np.ndarray, cells: int) -> np.ndarray:
    """(rows, cols) grid of the median depth of the points in each image cell of ``cam`` (the
    lower median; inf: no point), on the cells of :func:`atgs.geometry.free_space.nearest_depth_grid`."""
    idx, z, shape, _ = points_in_cells(cam, points, cells)
    grid = np.full(shape[0] * shape[1], np.inf)
    order = np.lexsort((z, idx))  # by cell, then by depth
    idx, z = idx[order], z[order]
    starts = np.flatnonzero(np.r_[True, idx[1:] != idx[:-1]]) if len(idx) else np.zeros(0, np.int64)
    counts = np.diff(np.r_[starts, len(idx)])
    grid[idx[starts]] = z[starts + (counts - 1) // 2]
    return grid.reshape(shape)


def measured_depth_grid(cam: Camera, points: np.ndarray, colors: np.ndarray, image: np.ndarray,
                        cell_px: float = CELL_PX) -> np.ndarray:
    """(rows, cols) median depth of the points ``cam`` sees (:func:`visible_points`) per cell of
    ``cell_px`` pixels, min-filtered over measured 3x3 cells; inf where no point."""
    seen = visible_points(cam, points, colors, image)
    return _min_filtered(median_depth_grid(cam, np.asarray(points)[seen], cells_of(cam, cell_px)))


@dataclass
class MeasuredDepths:
    """Per training camera (by its slot in ``cameras``), the measured depth per image cell:
    ``static`` over all keyframes, ``at_frame`` per measured frame (see the module's doc)."""

    cameras: list[Camera]
    cell: list[float]  # cell size in pixels, per camera
    static: list[torch.Tensor]  # (rows, cols) float32, inf: unmeasured
    at_frame: dict[int, list[torch.Tensor]]
    margin: float = MARGIN

    @classmethod
    def measure(cls, cameras: Sequence[Camera], parts: Sequence[tuple[int, np.ndarray, np.ndarray]],
                image_of: Callable[[int, int], np.ndarray], device: torch.device | str = "cpu",
                cell_px: float = CELL_PX, margin: float = MARGIN) -> "MeasuredDepths":
        """``parts``: (frame, points (P, 3), colours (P, 3) in [0, 1]) measured at that frame;
        ``image_of(slot, frame)``: camera ``cameras[slot]``'s (H, W, 3) uint8 image of a frame."""
        cams = list(cameras)
        at_frame: dict[int, list[np.ndarray]] = {}
        for frame, pts, cols in parts:
            grids = [measured_depth_grid(c, pts, cols, image_of(s, frame), cell_px) for s, c in enumerate(cams)]
            old = at_frame.get(frame)
            at_frame[frame] = grids if old is None else [np.minimum(a, b) for a, b in zip(old, grids)]
        static = [median_depth_grid(c, np.zeros((0, 3)), cells_of(c, cell_px)) for c in cams]  # all inf
        for grids in at_frame.values():
            static = [np.minimum(a, b) for a, b in zip(static, grids)]
        tensor = lambda g: torch.as_tensor(g, dtype=torch.float32, device=device)  # noqa: E731
        return cls(cams, [max(c.width, c.height) / cells_of(c, cell_px) for c in cams],
                   [tensor(g) for g in static], {f: [tensor(g) for g in gs] for f, gs in at_frame.items()}, margin)

    @property
    def any_measured(self) -> bool:
        return any(bool(torch.isfinite(g).any()) for g in self.static)

    def limits(self, slot: int, frame: int, means: torch.Tensor, moving: torch.Tensor) -> torch.Tensor:
        """(N,) measured depth along the ray of camera ``slot`` through each mean (N, 3): at a
        measured frame, the frame's own where it measured the ray; elsewhere the static depth for
        static Gaussians and nothing (inf) for ``moving`` ones; inf outside the image, behind the
        camera or unmeasured."""
        cam, cell = self.cameras[slot], self.cell[slot]
        u, v, z, inside = project(cam, means)
        static = self.static[slot]
        r = (v / cell).long().clamp(0, static.shape[0] - 1)
        c = (u / cell).long().clamp(0, static.shape[1] - 1)
        inf = torch.full_like(static[r, c], float("inf"))
        d = torch.where(moving, inf, static[r, c])
        frame_grids = self.at_frame.get(frame)
        if frame_grids is not None:  # measured now: the frame's own depth, for every Gaussian
            own = frame_grids[slot][r, c]
            d = torch.where(torch.isfinite(own), own, d)
        return torch.where(inside, d.to(means.dtype), torch.full_like(z, float("inf")))

    def pixel_depths(self, slot: int, frame: int) -> torch.Tensor:
        """(H, W) measured depth of each pixel of camera ``slot``: the frame's own where it
        measured the pixel, else the static one (inf: unmeasured)."""
        cam, cell = self.cameras[slot], self.cell[slot]
        grid = self.static[slot]
        own = self.at_frame.get(frame)
        if own is not None:
            grid = torch.where(torch.isfinite(own[slot]), own[slot], grid)
        rows = (torch.arange(cam.height, device=grid.device) + 0.5) / cell
        cols = (torch.arange(cam.width, device=grid.device) + 0.5) / cell
        r = rows.long().clamp(0, grid.shape[0] - 1)
        c = cols.long().clamp(0, grid.shape[1] - 1)
        return grid[r][:, c]
