"""Packing drops non-finite Gaussians (and only those) and keeps the rest bit for bit."""

from __future__ import annotations

import numpy as np
import torch

from atgs.gaussians import Gaussians
from atgs.viewer.packing import pack_gaussians
from atgs.viewer.source import SyntheticSource


def _gaussians(n: int) -> Gaussians:
    gen = torch.Generator().manual_seed(0)
    return Gaussians(torch.randn(n, 3, generator=gen), torch.randn(n, 4, generator=gen),
                     torch.rand(n, 3, generator=gen) * 0.1 + 0.01, torch.rand(n, generator=gen),
                     torch.rand(n, 3, generator=gen))


def test_non_finite_gaussians_are_dropped() -> None:
    g = _gaussians(50)
    bad = {3: ("means", float("nan")), 17: ("scales", float("inf")), 31: ("colors", float("-inf")),
           40: ("opacities", float("nan")), 44: ("quats", float("nan"))}
    for i, (field, value) in bad.items():
        t = getattr(g, field)
        if t.dim() == 1:
            t[i] = value
        else:
            t[i, 0] = value
    packed = pack_gaussians(g)
    keep = [i for i in range(50) if i not in bad]
    finite = Gaussians(*(t[keep] for t in g.as_tuple()))
    expect = pack_gaussians(finite)
    assert len(packed) == 45
    np.testing.assert_array_equal(packed.data, expect.data)
    np.testing.assert_array_equal(packed.means, g.means[keep].numpy())


def test_synthetic_source_frames_are_fresh_float32_copies() -> None:
    src = SyntheticSource(num_gaussians=200, frames=5)
    a = src.gaussians_at_frame(2)
    assert all(t.dtype == torch.float32 for t in a.as_tuple())
    a.colors[:] = 0.0  # a caller modifying its frame must not change later frames
    b = src.gaussians_at_frame(2)
    assert float(b.colors.max()) > 0.1
    np.testing.assert_allclose(b.quats.numpy(), src._quats.astype(np.float32))
    np.testing.assert_allclose(b.means.numpy(), src.gaussians_at_frame(2).means.numpy())
