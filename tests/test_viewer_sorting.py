"""The depth sort and cull (atgs/viewer/sorting.py): the plane form of the screen-space cull against
the pixel-space bound written out in numpy, and the same order on CPU and CUDA."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from atgs.cameras import look_at
from atgs.viewer.sorting import FrustumCull, back_to_front
from atgs.viewer.splat_renderer import clamp_limits

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (torch sees none)")


def _scene(n: int, seed: int):
    gen = np.random.default_rng(seed)
    means = (gen.uniform(-1, 1, (n, 3)) * [14.0, 8.0, 8.0]).astype(np.float32)
    extent = np.exp(gen.normal(-2.0, 1.2, n)).astype(np.float32)
    opacity = gen.uniform(0, 1, n).astype(np.float32)
    K = np.array([[60.0, 0, 31.0], [0, 58.0, 25.0], [0, 0, 1]])
    w2c = look_at(np.array([0.5, -7.0, 1.5]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
    return means, extent, opacity, K, w2c


def _pixel_bound_keep(means, extent, opacity, K, w2c, W, H, near, min_alpha, mod) -> tuple[np.ndarray, np.ndarray]:
    """float64: z > near, opacity >= cutoff, and the splat's pixel disc u +- r, v +- r with
    r = 3 (||J||_F m extent / z + sqrt(0.3)) + 1 overlapping the image; also each Gaussian's
    margin (how far inside the tightest test it is, in pixels) to tell ties apart."""
    p = means.astype(np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
    x, y, z = p.T
    zs = np.where(z > near, z, 1.0)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    lim = clamp_limits(K, W, H)
    lx, ly = max(lim[0], lim[1]), max(lim[2], lim[3])
    jf = math.sqrt(fx**2 * (1 + lx * lx) + fy**2 * (1 + ly * ly))
    r = 3.0 * (jf * mod * extent / zs + math.sqrt(0.3)) + 1.0
    u, v = fx * x / zs + cx, fy * y / zs + cy
    margin = np.minimum.reduce([u + r, W - (u - r), v + r, H - (v - r)])
    keep = (z > near) & (opacity >= np.float32(min_alpha)) & (margin > 0)
    return np.flatnonzero(keep), margin


def test_plane_cull_equals_the_pixel_bound() -> None:
    means, extent, opacity, K, w2c = _scene(20000, seed=2)
    W, H = 64, 48
    for mod, cutoff in ((1.0, 1 / 255), (0.5, 8 / 255)):
        cull = FrustumCull(K, W, H, clamp_limits(K, W, H), scale_modifier=mod)
        got = np.sort(back_to_front(means, w2c, 0.01, extent=extent, cull=cull, opacity=opacity,
                                    min_alpha=cutoff).numpy())
        expect, margin = _pixel_bound_keep(means, extent, opacity, K, w2c, W, H, 0.01, cutoff, mod)
        assert 0.05 * len(means) < len(expect) < 0.6 * len(means)  # both kinds occur
        differ = np.setxor1d(got, expect)
        assert np.all(np.abs(margin[differ]) < 1e-3), "only float32 ties may go either way"


@needs_cuda
def test_cuda_sorts_like_the_cpu() -> None:
    means, extent, opacity, K, w2c = _scene(50000, seed=3)
    cull = FrustumCull(K, 64, 48, clamp_limits(K, 64, 48))
    args = dict(extent=extent, cull=cull, opacity=opacity, min_alpha=1 / 255)
    for exact in (False, True):
        cpu = back_to_front(torch.from_numpy(means), w2c, 0.01, exact=exact, **args).numpy()
        gpu = back_to_front(torch.from_numpy(means).cuda(), w2c, 0.01, exact=exact,
                            **{**args, "extent": torch.from_numpy(extent).cuda(),
                               "opacity": torch.from_numpy(opacity).cuda()})
        assert gpu.device.type == "cuda"
        gpu = gpu.cpu().numpy()
        assert np.setxor1d(cpu, gpu).size <= 2  # float32 ties at the cull boundary
        z = means.astype(np.float64) @ w2c[2, :3] + w2c[2, 3]
        step = (z[cpu].max() - z[cpu].min()) / 65535
        assert np.all(np.diff(z[gpu]) <= (1e-6 if exact else 1.01 * step))  # far to near
