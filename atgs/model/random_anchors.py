"""Random static anchors outside the space the keyframe points show to be empty.

The CPU presets add anchors sampled in the scene bounds (``ModelConfig.random_anchors``) so that
surfaces the sparse points miss can still be learned. Sampled uniformly in the box, many land
between the cameras and the surfaces they see; a camera whose view they cross is then fitted
with them, and a camera held out from training sees them as floaters (on the real N3DV frame
dropping the Gaussians within 5 m of that camera raised its PSNR by 4.6 dB; docs/model.md).

A keyframe point seen by a camera shows that the segment between the camera and the point is
empty. Each training camera keeps, per cell of a coarse grid over its image, the depth of the
nearest point in the cell; a sample lying in front of that depth (by more than ``margin`` of it)
in any camera is in empty space and is rejected. Cells without points carve nothing, so unseen
and unmeasured space keeps its samples. Samples no training camera sees are rejected too: no
image would ever train them.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from atgs.cameras import Camera

GRID_CELLS = 32  # cells along each image's long side
MARGIN = 0.8  # a sample at depth < MARGIN x the cell's nearest point depth is in empty space
OVERSAMPLE = 8  # candidates drawn per wanted anchor, in rounds, before giving up


def nearest_depth_grid(cam: Camera, points: np.ndarray, cells: int = GRID_CELLS) -> tuple[np.ndarray, float]:
    """(rows, cols) grid of the nearest point depth per image cell of ``cam`` (inf: no point),
    and the cell size in pixels."""
    cell = max(cam.width, cam.height) / cells
    rows, cols = int(np.ceil(cam.height / cell)), int(np.ceil(cam.width / cell))
    grid = np.full(rows * cols, np.inf)
    if len(points):
        uv, z = cam.project(points)
        with np.errstate(invalid="ignore"):
            ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        idx = (uv[ok, 1] // cell).astype(np.int64) * cols + (uv[ok, 0] // cell).astype(np.int64)
        np.minimum.at(grid, idx, z[ok])
    return grid.reshape(rows, cols), cell


def carve(samples: np.ndarray, points: np.ndarray, cameras: Sequence[Camera], margin: float = MARGIN,
          cells: int = GRID_CELLS) -> np.ndarray:
    """(N,) bool: the samples seen by at least one camera and in front of no camera's points."""
    keep = np.ones(len(samples), bool)
    seen = np.zeros(len(samples), bool)
    for cam in cameras:
        grid, cell = nearest_depth_grid(cam, points, cells)
        uv, z = cam.project(samples)
        with np.errstate(invalid="ignore"):
            inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        r = np.clip((uv[inside, 1] // cell).astype(np.int64), 0, grid.shape[0] - 1)
        c = np.clip((uv[inside, 0] // cell).astype(np.int64), 0, grid.shape[1] - 1)
        empty = np.zeros(len(samples), bool)
        nearest = grid[r, c]
        empty[inside] = np.isfinite(nearest) & (z[inside] < margin * nearest)  # no point: nothing carved
        keep &= ~empty
        seen |= inside
    return keep & seen


def random_anchor_points(n: int, box: torch.Tensor, points: torch.Tensor, cameras: Sequence[Camera],
                         generator: torch.Generator, margin: float = MARGIN) -> torch.Tensor:
    """Up to ``n`` points uniform in ``box`` (2,3) that ``carve`` keeps (fewer where little space
    is left after OVERSAMPLE x n candidates; without cameras, plain uniform samples)."""
    lo, size = box[0].float(), (box[1] - box[0]).float()
    if not cameras:
        return lo + torch.rand(n, 3, generator=generator, device=generator.device) * size
    pts = points.detach().double().cpu().numpy()
    kept: list[torch.Tensor] = []
    total = 0
    for _ in range(OVERSAMPLE):
        cand = lo + torch.rand(n, 3, generator=generator, device=generator.device) * size
        ok = torch.as_tensor(carve(cand.double().cpu().numpy(), pts, cameras, margin), device=cand.device)
        kept.append(cand[ok])
        total += int(ok.sum())
        if total >= n:
            break
    return torch.cat(kept)[:n]
