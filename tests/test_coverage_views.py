"""Training cameras per measured pixel (atgs.geometry.coverage.views_per_pixel, scene_coverage): the
fast path against the pixel-by-point reference, exact counts on an analytic plane and occluder,
a sparse rig against a dense ring of the same scene, and what atgs-prepare prints."""

from __future__ import annotations

import numpy as np
import pytest

from atgs.cameras import Camera, look_at
from atgs.data.keyframe_points import _report
from atgs.geometry.coverage import front_points, scene_coverage, seen_by, views_per_pixel, views_per_pixel_reference
from test_data_mvs import BOX, GROUND, ring


@pytest.mark.parametrize("spacing", [0.02, 0.1, 0.3])
def test_views_per_pixel_matches_the_reference(spacing: float) -> None:
    rng = np.random.default_rng(int(spacing * 100))
    cams = ring(5, w=100, h=75)  # the z-buffer (80 px) and the working resolution (40 px) both downscale
    pts = np.concatenate([rng.uniform([-1.5, -1.5, 0], [1.5, 1.5, 1.0], (120, 3)),
                          rng.uniform(-4, 4, (20, 3))])  # some behind or beside the cameras
    fast = views_per_pixel(cams, pts, spacing, test=["cam02"], long_side=40)
    slow = views_per_pixel_reference(cams, pts, spacing, test=["cam02"], long_side=40)
    for f, s in zip(fast, slow):
        assert np.array_equal(f, s)
    counts = np.concatenate([f[f >= 0] for f in fast])
    assert counts.min() <= 2 and counts.max() == 4  # some occlusion, and points that every training camera sees


def _grid(center: np.ndarray, half: float, step: float = 0.01) -> np.ndarray:
    """Points of the axis-aligned square ``|x - cx|, |y - cy| <= half`` at height ``center[2]``."""
    g = np.arange(-half, half + step / 2, step)
    x, y = np.meshgrid(g, g)
    return np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1) + center


def _plane_rig(n: int = 4) -> list[Camera]:
    """``n`` cameras 3 above the plane z = 0, 0.85 off its center, each seeing all of [-0.5, 0.5]^2."""
    K = np.array([[110.0, 0, 32], [0, 110.0, 24], [0, 0, 1]])
    eyes = [np.array([0.6 * np.cos(a) - 0.6 * np.sin(a), 0.6 * np.sin(a) + 0.6 * np.cos(a), 3.0])
            for a in np.arange(n) * 2 * np.pi / n]
    return [Camera(f"cam{i}", 64, 48, K, look_at(e, np.zeros(3), up=np.array([0.0, 1.0, 0.0])))
            for i, e in enumerate(eyes)]


def test_a_plane_seen_by_k_cameras_has_exactly_k() -> None:
    plane = _grid(np.zeros(3), 0.5)
    for k in (1, 2, 4):
        maps = views_per_pixel(_plane_rig(k), plane, 0.01)
        assert all(np.all(m[m >= 0] == k) and (m >= 0).mean() > 0.3 for m in maps)
    cov = scene_coverage(_plane_rig(4), plane, np.zeros(len(plane), np.int64), 1, test_cameras=["cam3"])
    v = cov["views_per_pixel"]
    assert v["mean"] == 3.0 and v["test_cameras"] == {"cam3": 3.0}  # a held-out camera does not count itself
    assert set(v["per_camera"]) == set(cov["per_camera"]) and cov["test_cameras"]["cam3"] > 0.3


def test_a_point_hidden_behind_a_nearer_surface_does_not_count_that_camera() -> None:
    cams = _plane_rig(4)
    eye0 = cams[0].center
    plane = _grid(np.zeros(3), 0.5)
    # a square halfway between camera 0 and the plane's center: its shadow from camera 0 is |x|, |y| <= 0.2
    # (the segment eye0 -> P crosses z = eye0_z / 2 at (eye0 + P) / 2); the other cameras do not see it
    occluder = _grid(eye0 / 2, 0.1)
    pts = np.concatenate([plane, occluder])
    seen = seen_by(cams, pts, 0.01)
    r = np.abs(plane[:, :2]).max(1)
    assert not seen[0, : len(plane)][r < 0.15].any() and seen[0, : len(plane)][r > 0.3].all()
    assert seen[1:, : len(plane)].all() and seen[0, len(plane):].all() and not seen[1:, len(plane):].any()
    maps = views_per_pixel(cams, pts, 0.01)
    shown = [front_points(c, pts, 0.01) for c in cams]
    # camera 0 shows the occluder (seen by camera 0 alone) where the plane is hidden, the plane elsewhere
    assert np.array_equal(maps[0], np.where(shown[0] < 0, -1, np.where(shown[0] >= len(plane), 1, 4)))
    shown_r = np.abs(pts[np.maximum(shown[1], 0), :2]).max(-1)
    hidden = (shown[1] >= 0) & (shown_r < 0.15)
    assert np.all(maps[1][hidden] == 3) and np.all(maps[1][(shown[1] >= 0) & (shown_r > 0.3)] == 4)
    assert hidden.sum() > 100 and np.all(shown[1] < len(plane))


def _ground_and_box(n: int) -> np.ndarray:
    """``n`` points uniform over the visible surfaces of the ring's scene: the ground square
    (outside the box's footprint) and the box's top and sides."""
    rng = np.random.default_rng(0)
    lo, hi = BOX
    size = hi - lo
    areas = np.array([size[0] * size[1], *[size[1] * size[2]] * 2, *[size[0] * size[2]] * 2])  # top, -x, +x, -y, +y
    axis, value = np.array([2, 0, 0, 1, 1]), np.array([hi[2], lo[0], hi[0], lo[1], hi[1]])
    n_box = round(n * areas.sum() / (areas.sum() + (2 * GROUND) ** 2 - size[0] * size[1]))
    face = rng.choice(5, n_box, p=areas / areas.sum())
    box = rng.uniform(lo, hi, (n_box, 3))
    box[np.arange(n_box), axis[face]] = value[face]
    g = rng.uniform(-GROUND, GROUND, (2 * n, 2))
    g = g[np.any((g < lo[:2]) | (g > hi[:2]), axis=1)][: n - n_box]
    return np.concatenate([box, np.column_stack([g, np.zeros(len(g))])])


def test_a_sparse_rig_reads_lower_than_a_dense_ring_of_the_same_scene() -> None:
    pts = _ground_and_box(8000)
    figure = {n: scene_coverage(ring(n), pts, np.zeros(len(pts), np.int64), 1)["views_per_pixel"]["mean"]
              for n in (3, 12)}
    assert 1 <= figure[3] <= 3 < 6 < figure[12] <= 12, figure


def _cov(mean_views: float) -> dict:
    return {"mean": 0.74, "test_cameras": {"cam00": 0.87}, "per_camera": {},
            "views_per_pixel": {"mean": mean_views, "test_cameras": {"cam00": 2.94}, "per_camera": {}}}


COUNTS = {"sift": [300], "stereo": [8000], "fill": [0], "extend": [50]}


def test_report_prints_the_views_on_the_coverage_line(capsys) -> None:
    _report(COUNTS, _cov(3.14), ["cam00"], progress=True, cams=ring(12))
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["keyframe points (mean of 1): 300 SIFT + 8000 stereo + 0 fill + 50 extension; coverage of the "
                   "training cameras by SIFT + stereo 74%, seen by 3.1 training cameras per measured pixel; "
                   "test cam00 87% seen by 2.9"]


def test_report_warns_about_a_sparse_rig(capsys) -> None:
    _report(COUNTS, _cov(1.62), ["cam00"], progress=False, cams=ring(12))
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warning: a sparse rig (12 training cameras")
    assert "measured pixels seen by 1.6 of them" in err[0]
    _report(COUNTS, _cov(0.0), ["cam00"], progress=False, cams=ring(12))  # no measured pixel: nothing to say
    assert capsys.readouterr().err == ""
