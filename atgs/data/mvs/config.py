"""Knobs of the keyframe geometry: CPU multi-view stereo and the fallback fill (both exposed on
``atgs-prepare`` as ``--stereo.*`` and ``--fill.*``; docs/data.md explains each choice)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import tyro


@dataclass(frozen=True)
class StereoConfig:
    """Dense depth per camera by PatchMatch stereo, then cross-view fusion into keyframe points."""

    enabled: Annotated[bool, tyro.conf.arg(name="stereo", prefix_name=False)] = True
    """Dense multi-view stereo at every keyframe (--no-stereo: SIFT triangulation only)."""
    long_side: int = 400
    """Working resolution: images are box-downsampled to at most this many pixels on the long side."""
    window: int = 5
    """Side of the square NCC window, in working pixels (samples symmetric about the center)."""
    window_step: int = 2
    """Sample every n-th pixel of the window (5 px, step 2: 3 x 3 = 9 samples instead of 25)."""
    neighbors: int = 4
    """Source cameras per reference camera (chosen by triangulation angle and view overlap)."""
    top_k: int = 1
    """Matching costs averaged over the best k sources, so one occluded source does not break a pixel."""
    levels: int = 3
    """PatchMatch pyramid levels (each half the size of the next; 1: the working resolution only)."""
    coarse_iterations: int = 4
    """PatchMatch iterations at each coarser level, starting from random planes at the coarsest."""
    iterations: int = 1
    """PatchMatch iterations at the working resolution."""
    candidates: int = 3
    """Neighbour planes a pixel tests per iteration: its cheapest of 8 (at distances 1 and 3)."""
    geo_iterations: int = 1
    """Iterations of a second pass whose cost adds the disagreement with the sources' first-pass
    depth maps (0: no second pass)."""
    geo_weight: float = 0.2
    """Weight of that disagreement (pixels of round-trip reprojection error) against 1 - NCC."""
    geo_max_px: float = 3.0
    """The disagreement is truncated at this many pixels."""
    min_ncc: float = 0.3
    """Pixels whose mean NCC (best sources) is below this get no depth."""
    min_texture: float = 0.004
    """...nor pixels whose reference window has an intensity standard deviation below this (in [0,1])."""
    min_consistent: int = 2
    """Fusion keeps a depth only if at least this many other cameras' depths agree with it."""
    reproj_px: float = 1.0
    """Agreement: the point reprojects from the other camera within this many working pixels..."""
    rel_depth: float = 0.01
    """...and its depth differs by at most this fraction."""
    voxel_px: float = 2.0
    """Fused points are voxel-averaged; the voxel is this many working pixels at the median depth."""
    max_points: int = 8000
    """Per keyframe; the voxel grows until the fused points fit (0: no cap). Each point becomes an
    anchor: more points cost training time on a CPU; coverage does not drop with fewer (bench)."""
    threads: int = 0
    """Torch threads for the stereo (0: the cores the load average leaves idle, at least 1; on a
    busy machine one thread avoids the threads waiting for each other)."""


@dataclass(frozen=True)
class FillConfig:
    """Points in the space seen by at least two cameras where stereo and SIFT left pixels uncovered."""

    enabled: Annotated[bool, tyro.conf.arg(name="fill", prefix_name=False)] = True
    """Fill uncovered space so training can always start (--no-fill: never)."""
    below: float = 0.2
    """A training camera whose pixels are covered less than this fraction gets fill points."""
    points: int = 8000
    """Fill points per keyframe at most."""
    min_views: int = 2
    """A fill point must project inside at least this many cameras, within their near/far range."""
    extend_reach: float = 0.1
    """Extend the measured surfaces into each training camera's uncovered pixels up to this fraction
    of the image's long side from covered ones, at the depth of the nearest covered pixels
    (atgs.data.mvs.extend; 0: never)."""
    extend_points: int = 4000
    """Extension points per keyframe at most."""
