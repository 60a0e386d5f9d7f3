"""Per-camera exposure: a gain and a bias per colour channel for each training camera.

Real rigs do not expose their cameras alike (on the N3DV frame five of the twenty training
cameras are ~20 % brighter than the others). The model's colours do not depend on the view, so
without this it can only bend its geometry towards each camera's brightness, and a held-out
camera gets whatever blend of those compromises its rays meet: a colour cast that changes with
the seed (docs/training.md, "Camera exposure").

Training renders camera ``i`` as ``image * exp(g_i) + b_i``. The gauge is fixed by the mean:
the values used are ``g_i - mean(g)`` and ``b_i - mean(b)``, so the model's own colours are the
training cameras' average exposure, which is what held-out cameras and the viewer render (no
correction). A uniform shift of every camera's parameters changes nothing.
"""

from __future__ import annotations

import numpy as np
import torch


class CameraExposure:
    def __init__(self, num_cameras: int, lr: float, device: torch.device | str = "cpu") -> None:
        # (N, 6): log-gains of R, G, B, then biases; zeros are the identity
        self.table = torch.zeros(num_cameras, 6, device=device, requires_grad=True)
        self.opt = torch.optim.Adam([self.table], lr=lr, eps=1e-15)

    def start_from(self, gains: np.ndarray) -> None:
        """Start the log-gains at measured ``gains`` (cameras, 3), e.g. :func:`measured_exposure`'s."""
        g = torch.as_tensor(np.log(np.asarray(gains, dtype=np.float64)), dtype=torch.float32,
                            device=self.table.device)
        with torch.no_grad():
            self.table[:, :3] = g

    def gauge_fixed(self) -> torch.Tensor:
        """(N, 6) the parameters as used: every column minus its mean over the cameras."""
        return self.table - self.table.mean(0, keepdim=True)

    def gains_biases(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, 3) gains and (N, 3) biases, detached (for reports and checkpoints)."""
        p = self.gauge_fixed().detach()
        return p[:, :3].exp(), p[:, 3:]

    def apply(self, image: torch.Tensor, slot: int) -> torch.Tensor:
        """``image`` (H, W, 3) as training camera ``slot`` (its index among the training cameras) saw it."""
        p = self.gauge_fixed()[slot]
        return image * p[:3].exp() + p[3:]

    def step(self, clip: float) -> None:
        g = self.table.grad
        if g is None:
            return
        torch.nan_to_num_(g, nan=0.0, posinf=0.0, neginf=0.0)
        if clip > 0:
            torch.nn.utils.clip_grad_norm_([self.table], clip)
        self.opt.step()
        self.opt.zero_grad(set_to_none=True)

    def state_dict(self) -> dict:
        return {"table": self.table.detach().clone(), "opt": self.opt.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        table = state["table"].to(self.table.device)
        if table.shape != self.table.shape:
            raise ValueError(f"exposure table of {table.shape[0]} cameras, this run trains {self.table.shape[0]}")
        with torch.no_grad():
            self.table.copy_(table)
        self.opt.load_state_dict(state["opt"])


def measured_exposure(scene, cams: list[int], frame: int, points: np.ndarray, max_points: int = 4000,
                      min_views: int = 3, blur: int = 2, seed: int = 0, min_samples: int = 30) -> np.ndarray:
    """(len(cams), 3) each camera's gain per channel relative to the cameras' geometric mean,
    measured before training: the keyframe points are projected into the images of ``frame``
    (box-blurred over 2 * ``blur`` + 1 pixels against small misregistration), each point's
    reference colour is the median over the cameras that see it, and a camera's gain is the
    median of its colours over those references. Points seen by fewer than ``min_views`` cameras
    do not count; occluded ones are outvoted by the medians. NaN for a camera with fewer than
    ``min_samples`` such points."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) > max_points:
        pts = pts[np.random.default_rng(seed).choice(len(pts), max_points, replace=False)]
    cols = np.full((len(pts), len(cams), 3), np.nan)
    for k, ci in enumerate(cams):
        cam = scene.cameras[ci]
        img = _box_blur(scene.image_uint8(ci, frame)[..., :3].astype(np.float64) / 255.0, blur)
        h, w = img.shape[:2]
        uv, z = cam.project(pts)
        with np.errstate(invalid="ignore"):
            ok = (z > 0) & np.isfinite(uv).all(1)
        # images may be stored at another size than the camera's intrinsics
        with np.errstate(invalid="ignore"):
            u = np.floor(np.nan_to_num(uv[:, 0]) * w / cam.width).astype(np.int64)
            v = np.floor(np.nan_to_num(uv[:, 1]) * h / cam.height).astype(np.int64)
        ok &= (u >= blur) & (u < w - blur) & (v >= blur) & (v < h - blur)
        cols[ok, k] = img[v[ok], u[ok]]
    seen = np.isfinite(cols[..., 0]).sum(1) >= min_views
    cols = cols[seen]
    ref = np.nanmedian(cols, axis=1, keepdims=True)  # every row has >= min_views finite samples
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(ref > 0.05, cols / ref, np.nan)  # dark references say little about a gain
    gains = np.full((len(cams), 3), np.nan)
    for k in range(len(cams)):
        r = ratio[:, k]
        r = r[np.isfinite(r).all(1)]
        if len(r) >= min_samples:
            gains[k] = np.median(r, axis=0)
    good = np.isfinite(gains).all(1)
    if good.any():
        gains /= np.exp(np.log(gains[good]).mean(0))
    return gains


def _box_blur(img: np.ndarray, r: int) -> np.ndarray:
    if r <= 0:
        return img
    pad = np.pad(img, ((r, r), (r, r), (0, 0)), mode="edge")
    c = pad.cumsum(0).cumsum(1)
    c = np.pad(c, ((1, 0), (1, 0), (0, 0)))
    k = 2 * r + 1
    h, w = img.shape[:2]
    return (c[k:k + h, k:k + w] - c[:h, k:k + w] - c[k:k + h, :w] + c[:h, :w]) / (k * k)


def measure_scene_exposure(scene) -> np.ndarray:
    """:func:`measured_exposure` of a scene's training cameras at its first keyframe, from the
    points of that keyframe (all points when it has none); ones where nothing can be measured."""
    cams = list(scene.train_indices)
    cloud = scene.point_cloud
    first = cloud.read(0) if cloud.num_keyframes and cloud.count(0) else cloud.whole()[0]
    first = np.asarray(first, np.float64).reshape(-1, 3)
    if len(cams) < 2 or len(first) == 0:
        return np.ones((len(cams), 3))
    g = measured_exposure(scene, cams, int(scene.keyframes[0]), first)
    return np.where(np.isfinite(g), g, 1.0)
