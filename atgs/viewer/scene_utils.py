"""Camera helpers for the player and the video renderer: scene center, output sizes, paths."""

from __future__ import annotations

import math

import numpy as np
import torch

from atgs.cameras import Camera, look_at
from atgs.geometry.seen_space import axes_meeting_point
from atgs.rotations import matrix_slerp
from atgs.viewer.errors import ViewerError
from atgs.viewer.source import GaussianSource, decode_frame, scene_up


def parse_size(text: str | None) -> tuple[int, int] | None:
    """'WxH' -> (W, H)."""
    if text is None:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ViewerError(f"--size {text!r}: expected WIDTHxHEIGHT, e.g. 640x480") from None
    if not (1 <= w <= 16384 and 1 <= h <= 16384):
        raise ViewerError(f"--size {text!r}: width and height must be within 1..16384")
    return w, h


def resized(cam: Camera, size: tuple[int, int] | None) -> Camera:
    """The camera for an output of ``size`` (intrinsics scaled per axis; pixel-center convention)."""
    if size is None or size == (cam.width, cam.height):
        return cam
    w, h = size
    sx, sy = w / cam.width, h / cam.height
    K = cam.K.copy()
    K[0] *= sx
    K[1] *= sy
    return Camera(cam.name, w, h, K, cam.w2c.copy())


def look_center(cameras: list[Camera], fallback: np.ndarray | None = None) -> np.ndarray:
    """Least-squares point nearest to all optical axes (where a camera rig looks)."""
    meet = axes_meeting_point(cameras)
    if meet is not None:
        return meet
    if fallback is not None:
        return np.asarray(fallback, dtype=np.float64)
    if cameras:
        return cameras[0].center + cameras[0].forward
    return np.zeros(3)


def cloud_box(means: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Corners of the box holding a point cloud's bulk (2nd to 98th percentile: stray points
    far out do not shrink the view)."""
    if not len(means):
        return -np.ones(3), np.ones(3)
    lo, hi = np.percentile(np.asarray(means, dtype=np.float64), [2, 98], axis=0)
    return lo, hi


def default_camera(means: np.ndarray, size: tuple[int, int] = (640, 480)) -> Camera:
    """A camera that frames a point cloud (for sources without training cameras), looking at
    the centre of :func:`cloud_box`."""
    lo, hi = cloud_box(means)
    center = 0.5 * (lo + hi)
    radius = max(float(np.linalg.norm(hi - lo)) * 0.5, 1e-3)
    W, H = size
    f = 0.5 * H / math.tan(math.radians(25))
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    eye = center + radius * 2.5 * np.array([0.0, -1.0, 0.4]) / np.linalg.norm([0.0, -1.0, 0.4])
    return Camera("default", W, H, K, look_at(eye, center, np.array([0, 0, 1.0])))


def start_camera(source: GaussianSource, index: int) -> Camera:
    """Training camera ``index`` of the source (``--camera``), or a camera that frames frame 0
    when the source has no cameras."""
    cams = list(source.cameras)
    if not cams:
        return default_camera(decode_frame(source, 0).means.cpu().numpy())
    if not 0 <= index < len(cams):
        raise ViewerError(f"--camera {index}: the checkpoint has cameras 0..{len(cams) - 1}")
    return cams[index]


def orbit_center(source: GaussianSource) -> np.ndarray:
    """The pivot of orbits: where the training cameras look, or for a source without cameras
    (a 3DGS PLY) the point :func:`default_camera` looks at."""
    cams = list(source.cameras)
    if cams:
        return look_center(cams)
    with torch.no_grad():  # the means only: no packing (a PLY source keeps the frame it read last)
        lo, hi = cloud_box(source.gaussians_at_frame(0).means.cpu().numpy())
    return 0.5 * (lo + hi)


# A rig whose cameras leave a gap wider than this (radians of azimuth around the look centre;
# 150 degrees: three cameras 120 degrees apart still get a revolution) is front-facing: a full
# revolution would spend much of its frames behind what it captured.
FULL_ORBIT_MAX_GAP = math.radians(150.0)
MIN_SWEEP = math.radians(30.0)  # the narrowest sweep of a front-facing orbit


def covered_arc(azimuths: np.ndarray) -> tuple[float, float]:
    """(start, span) in radians of the smallest arc that holds every azimuth: the circle minus
    its largest gap between neighbouring cameras."""
    a = np.sort(np.mod(np.asarray(azimuths, dtype=np.float64), 2 * math.pi))
    if len(a) < 2:
        return (float(a[0]) if len(a) else 0.0), 0.0
    gaps = np.diff(np.append(a, a[0] + 2 * math.pi))
    k = int(np.argmax(gaps))  # the largest gap runs from a[k] to the next camera
    start = float(a[(k + 1) % len(a)])
    return start, float(2 * math.pi - gaps[k])


def orbit_path(cameras: list[Camera], n: int, center: np.ndarray | None = None) -> list[Camera]:
    """n cameras around the rig's look center, at the rig's mean radius and height, with the
    first training camera's intrinsics, looking at the center.

    A rig around the scene (no gap between cameras wider than 150 degrees of azimuth) gets one
    revolution. A front-facing rig gets a loop that sweeps to both ends of the arc its cameras
    cover and back (a sine in azimuth, starting at the arc's middle, at least 30 degrees wide), so
    no frame looks at the uncaptured back of the scene. A single camera gets a revolution."""
    if not cameras:
        raise ViewerError("orbit path needs at least one camera in the checkpoint")
    c0 = cameras[0]
    ctr = look_center(cameras) if center is None else np.asarray(center, dtype=np.float64)
    up = scene_up(cameras)
    offs = np.stack([c.center - ctr for c in cameras])
    height = float(np.mean(offs @ up))
    radial = offs - np.outer(offs @ up, up)
    radius = max(float(np.mean(np.linalg.norm(radial, axis=1))), 1e-3)
    e1 = radial[0] / max(np.linalg.norm(radial[0]), 1e-12)
    if np.linalg.norm(radial[0]) < 1e-9:
        e1 = np.cross(up, [1.0, 0, 0]) if abs(up[0]) < 0.9 else np.cross(up, [0, 1.0, 0])
        e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    start, span = covered_arc(np.arctan2(radial @ e2, radial @ e1))
    # one camera (a PLY without cameras gets a framing one) says nothing of what was captured
    full = len(cameras) == 1 or span >= 2 * math.pi - FULL_ORBIT_MAX_GAP
    if span < MIN_SWEEP:  # cameras close together still get some parallax
        start, span = start + 0.5 * span - 0.5 * MIN_SWEEP, MIN_SWEEP
    out = []
    for i in range(n):
        t = i / max(n, 1)
        a = 2 * math.pi * t if full else start + 0.5 * span * (1.0 + math.sin(2 * math.pi * t))
        eye = ctr + radius * (math.cos(a) * e1 + math.sin(a) * e2) + height * up
        out.append(Camera(f"orbit{i:05d}", c0.width, c0.height, c0.K.copy(), look_at(eye, ctr, up)))
    return out


def cameras_path(cameras: list[Camera], n: int) -> list[Camera]:
    """n cameras moving through the training cameras in order (position lerp, rotation slerp)."""
    if not cameras:
        raise ViewerError("camera path needs at least one camera in the checkpoint")
    if len(cameras) == 1 or n == 1:
        return [cameras[0]] * n
    out = []
    segs = len(cameras) - 1
    for i in range(n):
        u = i / (n - 1) * segs
        k = min(int(u), segs - 1)
        s = u - k
        a, b = cameras[k], cameras[k + 1]
        R = matrix_slerp(a.R.T, b.R.T, s).T  # interpolate camera-to-world rotations
        eye = (1 - s) * a.center + s * b.center
        K = (1 - s) * a.K + s * b.K
        w2c = np.eye(4)
        w2c[:3, :3] = R
        w2c[:3, 3] = -R @ eye
        out.append(Camera(f"path{i:05d}", a.width, a.height, K, w2c))
    return out
