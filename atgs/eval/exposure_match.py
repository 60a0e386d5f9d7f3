"""PSNR with each camera's own exposure fitted: the score of what a model can know.

A held-out camera's images carry its gain and black level. Training learns them for the training
cameras (atgs/train/exposure.py: a gain and a bias per colour channel), so their views are scored
with their own exposure; a held-out camera has none that training could learn, and the model
renders the training cameras' average. On a rig whose cameras differ by a third of a stop that
alone caps a perfect model near 16 dB, and hides whatever the geometry does (docs/evaluation.md,
"Exposure-matched PSNR").

``psnr_matched`` fits, for every evaluated camera, the same form the trainer learns (per channel
``y ~ gain x + bias``) by least squares over all that camera's evaluated views, then scores each
view after it (not clipped). Only the evaluated images enter the fit, never training; the fit has
six numbers per camera, so it cannot paint over fog or ghosts that vary across the image and over
time. Every camera gets the same rule (a training camera's fit starts from its learned exposure
and changes little).

The fit needs only per-view sums, so processes that split an evaluation's frames send sums, not
images: :func:`view_sums` per view, :func:`fit_camera` per camera, :func:`matched_psnr` per view.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

# per channel: count, sum x, sum y, sum x^2, sum xy, sum y^2 (x render, y ground truth)
SUMS = 6


def view_sums(render: torch.Tensor, gt: torch.Tensor) -> list[float]:
    """(3 x SUMS) sums of one view's (H, W, 3) render and ground truth, channel-major, in float64
    (in numpy: the scores leave the model's device, whatever torch's default device is)."""
    x = render.detach().cpu().numpy().reshape(-1, 3).astype(np.float64)
    y = gt.detach().cpu().numpy().reshape(-1, 3).astype(np.float64)
    n = np.full(3, float(x.shape[0]))
    cols = np.stack([n, x.sum(0), y.sum(0), (x * x).sum(0), (x * y).sum(0), (y * y).sum(0)], 1)
    return cols.reshape(-1).tolist()


def fit_camera(sums: Sequence[Sequence[float]]) -> tuple[list[float], list[float]]:
    """Per channel gain and bias minimising sum (gain x + bias - y)^2 over the views' ``sums``.
    A channel whose render does not vary gets gain 1 and the mean difference as its bias."""
    s = np.sum(np.asarray(sums, dtype=np.float64).reshape(len(sums), 3, SUMS), axis=0)
    gains, biases = [], []
    for n, sx, sy, sxx, sxy, _ in s:
        det = n * sxx - sx * sx
        if det <= 1e-12 * max(n * sxx, 1e-300):
            g = 1.0
        else:
            g = (n * sxy - sx * sy) / det
        gains.append(float(g))
        biases.append(float((sy - g * sx) / n))
    return gains, biases


def matched_psnr(sums: Sequence[float], gains: Sequence[float], biases: Sequence[float]) -> float:
    """PSNR (data range 1) of one view after ``gain x + bias`` per channel, from its sums."""
    s = np.asarray(sums, dtype=np.float64).reshape(3, SUMS)
    err = 0.0
    for (n, sx, sy, sxx, sxy, syy), g, b in zip(s, gains, biases):
        # sum (g x + b - y)^2 expanded
        err += g * g * sxx + 2 * g * b * sx + b * b * n - 2 * g * sxy - 2 * b * sy + syy
    count = float(s[:, 0].sum())
    mse = max(err, 0.0) / count
    return math.inf if mse == 0.0 else -10.0 * math.log10(mse)


def add_matched_psnr(rows: list[dict], key: str = "_exposure_sums") -> dict[str, dict[str, list[float]]]:
    """Give every row its ``psnr_matched`` (camera fitted over all its rows) and drop the sums;
    returns each camera's fitted {"gain", "bias"}."""
    by_camera: dict[str, list[dict]] = {}
    for r in rows:
        by_camera.setdefault(r["camera"], []).append(r)
    fits = {}
    for camera, own in by_camera.items():
        gains, biases = fit_camera([r[key] for r in own])
        fits[camera] = {"gain": gains, "bias": biases}
        for r in own:
            r["psnr_matched"] = matched_psnr(r.pop(key), gains, biases)
    return fits
