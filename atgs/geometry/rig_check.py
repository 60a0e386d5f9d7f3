"""Is a rig too sparse for honest novel views? Said once by atgs-prepare and again by atgs-train.

Two measured signs, either one enough:
- the measured pixels of the training cameras are seen by fewer than ``SPARSE_VIEWS`` training
  cameras on average (atgs.geometry.coverage: most of what one camera sees, no other confirms);
- at most ``FEW_CAMERAS`` training cameras whose nearest neighbours are more than
  ``WIDE_DEG`` apart as seen from where the rig's axes meet (optical axes, for parallel rigs).
Such a rig fits its training views and little else: Gaussians can explain one camera's pixels
in places the others cannot check, and a held-out camera sees them as floaters. What such rigs
gave is measured in docs/data.md ("Capture rigs, end to end") and quoted in the warning.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from atgs.cameras import Camera
from atgs.geometry.seen_space import meeting_depth

SPARSE_VIEWS = 2.0
FEW_CAMERAS = 6
WIDE_DEG = 50.0
# measured (bench/rigs.py): what to expect, in the user's words
EXPECTED = ("a synthetic 4-camera rig 90 degrees apart gave about 14 dB on its held-out camera against 29 dB on "
            "the training views")


def neighbour_angle_deg(cams: Sequence[Camera]) -> float:
    """Median over the cameras of the angle to the nearest other camera, seen from the point
    where the optical axes meet (the angle between optical axes for parallel rigs)."""
    if len(cams) < 2:
        return 180.0
    c = np.array([x.center for x in cams])
    t = meeting_depth(cams[0], cams)
    if t is not None:
        target = cams[0].center + t * cams[0].forward
        d = c - target
    else:
        d = np.array([x.forward for x in cams])
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(d @ d.T, -1, 1)))
    np.fill_diagonal(ang, np.inf)
    return float(np.median(ang.min(axis=1)))


def sparse_rig_warning(cams: Sequence[Camera], views_per_pixel: float | None) -> str | None:
    """The one-line warning for a rig too sparse for honest novel views, else None."""
    angle = neighbour_angle_deg(cams)
    few_wide = len(cams) <= FEW_CAMERAS and angle > WIDE_DEG
    thin = views_per_pixel is not None and 0 < views_per_pixel < SPARSE_VIEWS
    if not (few_wide or thin):
        return None
    what = [f"{len(cams)} training cameras, neighbours {angle:.0f} degrees apart"]
    if views_per_pixel:
        what.append(f"measured pixels seen by {views_per_pixel:.1f} of them")
    return (f"warning: a sparse rig ({', '.join(what)}): novel views away from the training cameras will be poor "
            f"({EXPECTED}); more cameras, or cameras closer together, are what helps")
