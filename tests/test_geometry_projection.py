"""atgs.geometry's projection and rays against a point-by-point reference: each point built at a
chosen pixel and depth (so where it must land is known), the in-front-and-inside test decided
one point at a time with plain comparisons, the numpy and torch paths held to each other."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from atgs.cameras import Camera, look_at
from atgs.geometry.projection import in_image, project
from atgs.geometry.rays import grid_rays, pixel_centres, pixel_rays, to_world

W, H = 40, 30


def _camera() -> Camera:
    K = np.array([[52.0, 0, 21.5], [0, 47.0, 13.0], [0, 0, 1]])  # off-centre, non-square pixels
    return Camera("c", W, H, K, look_at(np.array([2.0, -1.5, 1.0]), np.zeros(3), np.array([0, 0, 1.0])))


def _pixels_and_depths(n: int = 400) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel positions reaching past every edge, and depths on both sides of the camera."""
    rng = np.random.default_rng(1)
    u = rng.uniform(-5, W + 5, n)
    v = rng.uniform(-5, H + 5, n)
    z = rng.choice([-1.0, 1e-10, 0.5, 3.0], n) * rng.uniform(0.5, 1.5, n)
    u[:4], v[:4], z[:4] = [0.0, W, 0.0, W - 1e-6], [0.0, 0.0, H, H - 1e-6], 1.0  # the edges themselves
    return u, v, z


def _points(cam: Camera, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
    """World points seen at pixel (u, v) and depth z, built without atgs.geometry."""
    pc = np.stack([(u - cam.cx) * z / cam.fx, (v - cam.cy) * z / cam.fy, z], 1)
    return (pc - cam.t) @ cam.R


def _case() -> tuple[Camera, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The camera, the chosen pixels and depths, and the world points seen there."""
    cam = _camera()
    u, v, z = _pixels_and_depths()
    return cam, u, v, z, _points(cam, u, v, z)


@pytest.mark.parametrize("near", [0.0, 1e-9, 0.7])
def test_in_front_and_inside_one_point_at_a_time(near: float) -> None:
    cam, u, v, z, X = _case()
    pu, pv, pz, inside = project(cam, X, near)
    np.testing.assert_allclose(pz, z, rtol=1e-9, atol=1e-12)
    front = z > 1e-3  # far enough in front that the pixel is well conditioned
    np.testing.assert_allclose(pu[front], u[front], atol=1e-7)
    np.testing.assert_allclose(pv[front], v[front], atol=1e-7)
    want = [bool(zi > near and 0 <= ui < W and 0 <= vi < H) for ui, vi, zi in zip(pu, pv, pz)]
    assert inside.tolist() == want
    assert 0 < sum(want) < len(want)


@pytest.mark.parametrize("near", [0.0, 0.7])
def test_tensors_project_as_arrays(near: float) -> None:
    cam, u, v, z, X = _case()
    nu, nv, nz, n_inside = project(cam, X, near)
    tu, tv, tz, t_inside = project(cam, torch.as_tensor(X), near)
    assert isinstance(t_inside, torch.Tensor) and t_inside.dtype == torch.bool
    # (within 1e-9 of the camera plane the tensor path divides by the clamped depth: left out)
    sure = np.abs(z) > 1e-6
    assert sure.sum() > len(z) // 2
    assert t_inside.numpy()[sure].tolist() == n_inside[sure].tolist()
    ok = n_inside & sure
    np.testing.assert_allclose(tu.numpy()[ok], nu[ok], atol=1e-9)
    np.testing.assert_allclose(tv.numpy()[ok], nv[ok], atol=1e-9)
    np.testing.assert_allclose(tz.numpy(), nz, atol=1e-12)


def test_in_image_refuses_nan() -> None:
    cam = _camera()
    assert in_image(cam, np.array([np.nan, 1.0]), np.array([1.0, np.nan])).tolist() == [False, False]


def test_rays_land_back_on_their_pixels() -> None:
    cam = _camera()
    u, v, z = _pixels_and_depths()
    keep = z > 0.1
    u, v, z = u[keep], v[keep], z[keep]
    X = to_world(cam, pixel_rays(cam, u, v) * z[:, None])
    np.testing.assert_allclose(X, _points(cam, u, v, z), atol=1e-12)
    tX = pixel_rays(cam, torch.as_tensor(u), torch.as_tensor(v), dim=0)
    assert tX.shape == (3, len(u))
    np.testing.assert_array_equal(tX.T.numpy(), pixel_rays(cam, u, v))


def test_inverse_intrinsics_rays_agree_with_the_division() -> None:
    cam = _camera()
    cu, cv = pixel_centres(cam)
    assert cu.shape == (W * H,) and float(cu[W + 1]) == 1.5 and float(cv[W + 1]) == 1.5  # row-major
    by_inverse = pixel_rays(cam, cu, cv, dim=0, inverse_intrinsics=True)
    np.testing.assert_allclose(by_inverse.numpy(), pixel_rays(cam, cu, cv, dim=0).numpy(), atol=1e-14)


def test_grid_rays_pass_through_cell_centres() -> None:
    cam = _camera()
    rays = grid_rays(cam, 4)
    X = to_world(cam, rays * 2.0)
    pu, pv, _, inside = project(cam, X)
    assert inside.all()
    np.testing.assert_allclose(np.sort(np.unique(np.round(pu, 9))), (np.arange(4) + 0.5) * W / 4)
    np.testing.assert_allclose(np.sort(np.unique(np.round(pv, 9))), (np.arange(4) + 0.5) * H / 4)
