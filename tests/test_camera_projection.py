"""The torch pinhole of atgs.cameras (to_camera_frame, pinhole_pixels, pinhole_jacobian) against
Camera.project (numpy, float64) and its finite differences."""

from __future__ import annotations

import numpy as np
import torch

from atgs.cameras import Camera, look_at, pinhole_jacobian, pinhole_pixels, to_camera_frame


def _cameras() -> list[Camera]:
    K = np.array([[70.0, 0, 33.5], [0, 64.0, 22.0], [0, 0, 1]])  # off-centre, non-square pixels
    eyes = [(3.0, -1.0, 1.5), (-2.0, 2.5, 0.3), (0.5, 0.2, -3.0)]
    return [Camera(f"c{i}", 64, 48, K, look_at(np.array(e), np.zeros(3), np.array([0, 0, 1.0])))
            for i, e in enumerate(eyes)]


def _points(n: int = 200) -> np.ndarray:
    return np.random.default_rng(0).uniform(-1.0, 1.0, (n, 3))


def test_pixels_and_depths_match_camera_project() -> None:
    X = _points()
    for cam in _cameras():
        uv, z = cam.project(X)
        for dtype, atol in ((torch.float64, 1e-9), (torch.float32, 2e-4)):
            pc = to_camera_frame(cam, torch.as_tensor(X, dtype=dtype))
            assert pc.dtype == dtype
            u, v = pinhole_pixels(cam, pc, pc[:, 2])
            np.testing.assert_allclose(pc[:, 2].double().numpy(), z, atol=atol)
            np.testing.assert_allclose(torch.stack([u, v], 1).double().numpy(), uv, atol=atol * 100)


def test_distortion_is_not_applied() -> None:
    """Prepared scenes hold undistorted cameras; a camera with distortion projects as its pinhole."""
    cam = _cameras()[0]
    bent = Camera(cam.name, cam.width, cam.height, cam.K, cam.w2c, np.array([-0.2, 0.05, 0.001, -0.002]))
    X = _points()
    pc = to_camera_frame(bent, torch.as_tensor(X))
    uv = torch.stack(pinhole_pixels(bent, pc, pc[:, 2]), 1).numpy()
    np.testing.assert_allclose(uv, cam.project(X)[0], atol=1e-9)
    assert np.abs(uv - bent.project(X)[0]).max() > 0.5


def test_jacobian_matches_finite_differences_of_camera_project() -> None:
    X = _points(50)
    h = 1e-6
    for cam in _cameras():
        pc = to_camera_frame(cam, torch.as_tensor(X))
        J = pinhole_jacobian(cam, pc, pc[:, 2]).numpy()
        fd = np.stack([(cam.project(X + h * e)[0] - cam.project(X - h * e)[0]) / (2 * h) for e in np.eye(3)], -1)
        np.testing.assert_allclose(J, fd, rtol=1e-6, atol=1e-5)
