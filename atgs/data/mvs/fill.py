"""The fill of atgs-prepare: points in the space seen by at least two cameras where stereo and
SIFT leave a camera's pixels uncovered (textureless surfaces, very wide baselines, two to four
cameras). The samples and their colours come from atgs.geometry.seen_space (rays through the uncovered
pixels, kept where ``FillConfig.min_views`` cameras see them); training then starts from these
points and densification grows and prunes from there.

Image consistency (space carving: keep the samples whose colours agree across the cameras) was
tried and dropped: on a textured test scene it did not bring the fill closer to the surfaces
(docs/data.md), because depth samples sparse enough to be affordable rarely land within a
pixel's footprint of the surface.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from atgs.cameras import Camera
from atgs.data.mvs.config import FillConfig
from atgs.geometry.seen_space import seen_space_samples


def frustum_fill(cams: Sequence[Camera], ranges: Sequence[tuple[float, float]], cfg: FillConfig = FillConfig(),
                 images: Sequence[np.ndarray] | None = None, masks: Sequence[np.ndarray | None] | None = None,
                 seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Fill points (N,3) float64 and colours (N,3) float32 in [0,1] (0.5 grey without images):
    ``cfg.points`` at most, each seen by ``cfg.min_views`` cameras within their ``ranges``.

    ``masks[i]`` (H_i,W_i bool, any resolution) marks the pixels of camera i whose rays may be
    sampled (None: no rays from that camera; ``masks`` None: every pixel of every camera).
    """
    return seen_space_samples(cams, ranges, cfg.points, cfg.min_views, images, masks, seed)
