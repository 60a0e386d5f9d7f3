"""Dense keyframe geometry on the CPU: plane-sweep multi-view stereo, fusion, fallback fill.

One public entry per job:
- :func:`stereo_points`: coloured points of one keyframe from its images and posed cameras;
- :func:`atgs.data.mvs.fill.frustum_fill`: points in the space seen by at least two cameras.
"""

from __future__ import annotations

from atgs.data.mvs.config import FillConfig, StereoConfig
from atgs.data.mvs.stereo import StereoResult, stereo_points

__all__ = ["FillConfig", "StereoConfig", "StereoResult", "stereo_points"]
