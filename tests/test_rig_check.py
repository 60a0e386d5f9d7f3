"""The sparse-rig warning of atgs-prepare and atgs-train (atgs.geometry.rig_check)."""

import numpy as np
import pytest

from builders import ring_cameras
from atgs.cameras import Camera, look_at
from atgs.geometry.rig_check import neighbour_angle_deg, sparse_rig_warning


@pytest.mark.parametrize("n, angle", [(3, 120.0), (4, 90.0), (10, 36.0), (12, 30.0)])
def test_neighbour_angle_of_a_ring_is_its_spacing(n, angle):
    # the ring is level with what it looks at: the angle at the centre is the spacing
    assert neighbour_angle_deg(ring_cameras(n, height=0.0)) == pytest.approx(angle, abs=1e-6)


def test_a_front_facing_rig_uses_the_angle_between_its_axes():
    K = np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]])
    cams = [Camera(f"c{i}", 32, 24, K, look_at(np.array([0.3 * i, 0, 0]), np.array([0.3 * i, 5.0, 0]),
                                                np.array([0.0, 0, 1]))) for i in range(4)]
    assert neighbour_angle_deg(cams) == pytest.approx(0.0, abs=1e-6)
    assert sparse_rig_warning(cams, 3.0) is None


def test_the_warning_comes_for_few_wide_cameras_or_thin_measurements_only():
    assert sparse_rig_warning(ring_cameras(10, height=0.0), 3.5) is None  # a dense ring
    few = sparse_rig_warning(ring_cameras(3, height=0.0), 1.4)
    assert few is not None and few.startswith("warning: a sparse rig (3 training cameras, neighbours 120 degrees apart")
    assert "14 dB" in few and "\n" not in few
    thin = sparse_rig_warning(ring_cameras(12, height=0.0), 1.5)  # many cameras, but nothing confirmed twice
    assert thin is not None and "seen by 1.5 of them" in thin
    assert sparse_rig_warning(ring_cameras(12, height=0.0), None) is None
