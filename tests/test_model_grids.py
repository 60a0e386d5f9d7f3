"""Grids vs independent references: scipy multilinear interpolation, a slow per-point Python
hash, finite differences."""

import numpy as np
import pytest
import torch
from scipy.interpolate import RegularGridInterpolator

from atgs.model.grids import _PRIMES, HashGrid4D, SpatialGrid, gather_rows


def test_spatial_grid_matches_scipy_trilinear():
    g = SpatialGrid(5, 3)
    gen = torch.Generator().manual_seed(0)
    g.table = torch.randn(125, 3, generator=gen, dtype=torch.float64)
    x = torch.rand(50, 3, generator=gen, dtype=torch.float64)
    got, _ = g.query(x, track=False)
    # table row = ix + 5 (iy + 5 iz)  ->  dense[ix, iy, iz]
    dense = g.table.numpy().reshape(5, 5, 5, 3).transpose(2, 1, 0, 3)
    ax = np.linspace(0, 1, 5)
    ref = RegularGridInterpolator((ax, ax, ax), dense)(x.numpy())
    np.testing.assert_allclose(got.numpy(), ref, rtol=1e-10, atol=1e-12)
    out, _ = g.query(torch.tensor([[1.2, 0.5, 0.5], [-0.1, 0.2, 0.3]], dtype=torch.float64), track=False)
    assert torch.all(out == 0), "points outside the box get zero features"


def test_hash_grid_dense_levels_match_scipy_quadrilinear():
    # table big enough that every level is indexed densely (no collisions)
    h = HashGrid4D(2, levels=2, features=2, log2_table=12, base_res=3, growth=2.0, max_time_res=4)
    assert all(h.dense_level(lv) for lv in range(2))
    h.table = torch.randn(h.table.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    x = torch.rand(40, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    tau, grid = 0.37, 1
    got, _ = h.query(x, tau, grid, track=False)
    pts = np.concatenate([x.numpy(), np.full((40, 1), tau)], axis=1)
    for lv in range(2):
        r, rt = h.res[lv], h.time_res[lv]
        base = (grid * h.levels + lv) * h.table_size
        n = (r + 1) ** 3 * (rt + 1)
        # slot = x + (r+1)(y + (r+1)(z + (r+1) w))  ->  dense[x, y, z, w]
        dense = h.table[base: base + n].numpy().reshape(rt + 1, r + 1, r + 1, r + 1, 2).transpose(3, 2, 1, 0, 4)
        ax, at = np.linspace(0, 1, r + 1), np.linspace(0, 1, rt + 1)
        ref = RegularGridInterpolator((ax, ax, ax, at), dense)(pts)
        np.testing.assert_allclose(got[:, 2 * lv: 2 * lv + 2].numpy(), ref, rtol=1e-10, atol=1e-12)


def _slow_hash_query(h: HashGrid4D, x: np.ndarray, tau: float, grid: int) -> np.ndarray:
    """Per point, per level, per corner in plain Python integers."""
    T = h.table_size
    out = np.zeros((len(x), h.levels * h.features))
    table = h.table.numpy()
    for i, p in enumerate(x):
        q = [*p, tau]
        for lv in range(h.levels):
            res = [h.res[lv]] * 3 + [h.time_res[lv]]
            for c in range(16):
                w, v = 1.0, []
                for d in range(4):
                    pos = q[d] * res[d]
                    b = min(int(np.floor(pos)), res[d] - 1)
                    o = (c >> d) & 1
                    f = pos - b
                    w *= f if o else 1 - f
                    v.append(b + o)
                if h.dense_level(lv):
                    r1 = h.res[lv] + 1
                    slot = v[0] + r1 * (v[1] + r1 * (v[2] + r1 * v[3]))
                else:
                    hv = 0
                    for vi, pr in zip(v, _PRIMES):
                        hv ^= (vi * pr) & 0xFFFFFFFFFFFFFFFF
                    slot = hv % T
                out[i, lv * h.features:(lv + 1) * h.features] += w * table[(grid * h.levels + lv) * T + slot]
    return out


def test_hash_grid_hashed_levels_match_slow_reference():
    h = HashGrid4D(3, levels=3, features=2, log2_table=8, base_res=4, growth=2.0, max_time_res=8)
    assert not h.dense_level(2), "the finest level must use the hash"
    h.table = torch.randn(h.table.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    x = torch.rand(12, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    got, _ = h.query(x, 0.81, 2, track=False)
    np.testing.assert_allclose(got.numpy(), _slow_hash_query(h, x.numpy(), 0.81, 2), rtol=1e-10, atol=1e-12)


def test_gather_rows_gradient_is_sparse_and_matches_finite_differences():
    h = HashGrid4D(1, levels=2, features=2, log2_table=6, base_res=2, growth=2.0, max_time_res=2)
    h.table = torch.randn(h.table.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    x = torch.rand(5, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(6))
    wts = torch.randn(5, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(7))
    out, g = h.query(x, 0.3, 0, track=True)
    (out * wts).sum().backward()
    assert g.rows.numel() < h.table.shape[0], "only touched rows get a gradient"
    assert torch.equal(g.rows, torch.unique(g.rows))
    eps = 1e-6
    for k in range(0, g.rows.numel(), 3):
        for f in range(2):
            row = int(g.rows[k])
            tp, tm = h.table.clone(), h.table.clone()
            tp[row, f] += eps
            tm[row, f] -= eps
            h.table = tp
            op, _ = h.query(x, 0.3, 0, track=False)
            h.table = tm
            om, _ = h.query(x, 0.3, 0, track=False)
            fd = float(((op - om) * wts).sum()) / (2 * eps)
            assert g.leaf.grad[k, f].item() == pytest.approx(fd, rel=1e-5, abs=1e-8)


def test_gather_rows_equals_plain_indexing():
    table = torch.randn(20, 3)
    idx = torch.tensor([[3, 3, 7], [0, 19, 7]])
    a, g = gather_rows(table, idx, track=True)
    assert torch.equal(a, table[idx])
    assert g.rows.tolist() == [0, 3, 7, 19]
