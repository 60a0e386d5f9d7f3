"""Sparse optical flow: pyramidal Lucas-Kanade tracking of points between two frames (torch, CPU).

Used to start the per-keyframe anchors' velocities from the images (atgs.train.scene_flow).
Each point's window of the first image is compared with the second image at the tracked
position; the displacement is refined by Gauss-Newton steps in the inverse compositional form
(the first image's gradients and their 2x2 matrix are computed once per level), coarse to fine
over an image pyramid so that displacements of many pixels are found (Bouguet's formulation).
All points of a batch of image pairs (one per camera) are tracked at once: windows are read
with one ``grid_sample`` per step.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def pyramid(img: torch.Tensor, levels: int) -> list[torch.Tensor]:
    """(H, W) grey image, or a (B, H, W) batch of them -> ``levels`` (B, 1, h, w) images, finest
    first; each coarser level is blurred (binomial 1-2-1) and halved. Stops early when a level
    would have a side under 16 pixels."""
    k = torch.tensor([1.0, 2.0, 1.0], dtype=torch.float32, device=img.device) / 4.0
    x = img.float()
    out = [x[None, None] if x.dim() == 2 else x[:, None]]
    for _ in range(levels - 1):
        x = out[-1]
        if min(x.shape[-2:]) < 32:
            break
        x = F.conv2d(F.pad(x, (1, 1, 0, 0), mode="replicate"), k.view(1, 1, 1, 3))
        x = F.conv2d(F.pad(x, (0, 0, 1, 1), mode="replicate"), k.view(1, 1, 3, 1))
        out.append(F.avg_pool2d(x, 2, ceil_mode=True))
    return out


def _with_gradients(img: torch.Tensor) -> torch.Tensor:
    """(B, 1, h, w) -> (B, 3, h, w): the image and its central-difference x and y gradients."""
    p = F.pad(img, (1, 1, 1, 1), mode="replicate")
    gx = 0.5 * (p[..., 1:-1, 2:] - p[..., 1:-1, :-2])
    gy = 0.5 * (p[..., 2:, 1:-1] - p[..., :-2, 1:-1])
    return torch.cat([img, gx, gy], 1)


def sample(img: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    """Bilinear values (B, C, ...) of (B, C, h, w) ``img`` at pixel positions ``xy`` (B, ..., 2)
    (one set per image), pixel centres at integer + 0.5; the border replicates."""
    b, c = img.shape[:2]
    h, w = img.shape[-2:]
    scale = torch.tensor([2.0 / w, 2.0 / h], dtype=xy.dtype, device=xy.device)
    g = (xy * scale - 1.0).reshape(b, -1, 1, 2)
    v = F.grid_sample(img, g, mode="bilinear", padding_mode="border", align_corners=False)
    return v.reshape(b, c, *xy.shape[1:-1])


def track_points(first: list[torch.Tensor], second: list[torch.Tensor], xy: torch.Tensor, window: int = 9,
                 iterations: int = 10) -> tuple[torch.Tensor, torch.Tensor]:
    """Where the points ``xy`` (pixels of the finest level) of the images whose :func:`pyramid` is
    ``first`` are in the images of pyramid ``second``: (N, 2) points of one image pair, or
    (B, N, 2) points of each of B pairs.

    Returns (positions, residual) shaped like ``xy`` and ``xy[..., 0]``: the tracked positions and
    the RMS difference of the two windows there (in the images' units). A window without texture
    (a singular gradient matrix) keeps the displacement of the coarser level."""
    single = xy.dim() == 2
    pts = xy[None] if single else xy
    if pts.shape[1] == 0:
        return xy.clone(), xy.new_zeros(xy.shape[:-1])
    r = window // 2
    o = torch.arange(-r, r + 1, dtype=xy.dtype, device=xy.device)
    offs = torch.stack(torch.meshgrid(o, o, indexing="xy"), -1).reshape(1, 1, -1, 2)  # (1, 1, win^2, 2)
    guess = torch.zeros_like(pts)
    for lv in range(min(len(first), len(second)) - 1, -1, -1):
        s = float(2 ** lv)
        h, w = second[lv].shape[-2:]
        to_grid = torch.tensor([2.0 / w, 2.0 / h], dtype=xy.dtype, device=xy.device)  # pixels -> grid_sample units
        win = (pts / s)[:, :, None, :] + offs  # (B, N, win^2, 2)
        tg = sample(_with_gradients(first[lv]), win)  # (B, 3, N, win^2)
        t, gx, gy = tg[:, 0], tg[:, 1], tg[:, 2]  # (B, N, win^2) each
        gxx, gxy, gyy = (gx * gx).sum(-1), (gx * gy).sum(-1), (gy * gy).sum(-1)
        det = gxx * gyy - gxy * gxy
        ok = det > 1e-4 * (gxx + gyy) ** 2 + 1e-12  # well-conditioned: texture in two directions
        inv = torch.where(ok, 1.0 / det.clamp_min(1e-30), torch.zeros_like(det))
        base = (win * to_grid - 1.0).reshape(pts.shape[0], -1, 1, 2)  # the windows in grid units
        n_win = offs.shape[2]
        d = guess / s
        for _ in range(iterations):
            g = (base.view(pts.shape[0], -1, n_win, 2) + (d * to_grid)[:, :, None, :]).view_as(base)
            e = F.grid_sample(second[lv], g, mode="bilinear", padding_mode="border", align_corners=False)
            e = e.view(pts.shape[0], -1, n_win) - t
            bx, by = (e * gx).sum(-1), (e * gy).sum(-1)
            step = torch.stack([(gyy * bx - gxy * by) * inv, (gxx * by - gxy * bx) * inv], -1)
            d = d - step
            if float(step.abs().max()) < 0.02:
                break
        guess = d * s
    win = pts[:, :, None, :] + offs
    res = sample(second[0], win + guess[:, :, None, :])[:, 0] - sample(first[0], win)[:, 0]
    out, rms = pts + guess, res.pow(2).mean(-1).sqrt()
    return (out[0], rms[0]) if single else (out, rms)
