"""The model's near plane: how close to a camera a Gaussian may be and still be drawn.

Every renderer culls Gaussians at view-space z <= near. A fixed 0.01 scene units (gsplat's
default) means nothing on a capture-stage dome in metres, where cameras stand 3-5 m from the
content and see each other: a Gaussian a few centimetres in front of a lens covers the whole
view. The reference 3DGS rasterizer culls at z <= 0.2 in every scene; its synthetic (Blender)
scenes put the cameras 4 units from the content, where that is 0.05 of the camera distance.

So a model's near plane is a fraction (``ModelConfig.near_fraction``) of the median distance
from the *training* cameras' centres to the scene centre, fixed when the model is built and
saved with it: training, evaluation, atgs-view, atgs-render and the web player all cull with
the one value, whichever camera (a held-out one, the player's free camera) renders.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from atgs.cameras import Camera
from atgs.geometry.clearance import clearance_radius
from atgs.render.constants import NEAR


def near_plane(train_cameras: Sequence[Camera], scene_centre: np.ndarray, fraction: float) -> float:
    """``fraction`` of the median distance from the training cameras' centres to
    ``scene_centre``; the fixed :data:`~atgs.render.constants.NEAR` for a fraction of 0, no
    cameras, or cameras at the centre itself (no scale to measure)."""
    # (the clearance's rule: a fraction of the training cameras' median distance to the scene)
    near = clearance_radius(train_cameras, np.asarray(scene_centre, dtype=np.float64), fraction)
    return near if np.isfinite(near) and near > 0 else NEAR


def near_of(source: object) -> float:
    """The near plane to render ``source`` with: a model's own ``near``; the fixed
    :data:`~atgs.render.constants.NEAR` for anything without one (PLY files without an export
    manifest, synthetic scenes, test stand-ins)."""
    return float(getattr(source, "near", NEAR))
