"""Similarity alignment (Umeyama 1991) and pose-error measures, used to check SfM output."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from atgs.cameras import Camera


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Scale s, rotation R, translation t minimizing sum |s R src_i + t - dst_i|^2."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if src.shape != dst.shape or len(src) < 3:
        raise ValueError("umeyama needs two (N>=3, 3) arrays of the same shape")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    var_s = (xs ** 2).sum() / len(src)
    s = float(np.trace(np.diag(D) @ S) / var_s)
    t = mu_d - s * R @ mu_s
    return s, R, t


def pose_errors(estimated: Sequence[Camera], truth: Sequence[Camera]) -> tuple[np.ndarray, np.ndarray]:
    """Per-camera rotation error (degrees) and center error (truth units) after aligning the
    estimated camera centers to the true ones with a similarity transform."""
    ce = np.array([c.center for c in estimated])
    ct = np.array([c.center for c in truth])
    s, R, t = umeyama(ce, ct)
    rot_err, pos_err = [], []
    for e, g in zip(estimated, truth):
        # camera-to-world rotation of the estimate, mapped into the true frame
        Rc2w = R @ e.R.T
        dR = g.R @ Rc2w
        ang = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
        rot_err.append(ang)
        pos_err.append(np.linalg.norm(s * R @ e.center + t - g.center))
    return np.array(rot_err), np.array(pos_err)
