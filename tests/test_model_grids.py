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


# --- the compiled CPU kernels (atgs/render/csrc/grids.cpp) against the torch reference ---------

def _both(grid, query):
    """(torch reference, compiled) results of ``query(grid)`` on the same float32 table."""
    grid.backend = "torch"
    ref = query(grid)
    grid.backend = "auto"
    return ref, query(grid)


def _points(n: int, seed: int) -> torch.Tensor:
    x = torch.rand(n, 3, generator=torch.Generator().manual_seed(seed))
    # cell borders, the box faces and points outside it (clamped), as the decode sees them
    x[:6] = torch.tensor([[0, 0, 0], [1, 1, 1], [1, 0, 0.5], [-0.2, 1.3, 0.5], [0.5, 0.5, 0.5], [0.25, 0.75, 1]])
    return x


@pytest.mark.parametrize("log2_table", [8, 14])  # hashed fine levels / every level dense
def test_compiled_hash_grid_matches_torch_values_rows_and_gradients(log2_table):
    from atgs.model.grids import grid_kernels

    h = HashGrid4D(2, levels=5, features=2, log2_table=log2_table, base_res=3, growth=1.7, max_time_res=6,
                   generator=torch.Generator().manual_seed(8))
    assert grid_kernels(h.table, "auto") is not None, "the compiled grid kernels must build on this machine"
    x = _points(3000, 9)
    w = torch.randn(3000, 10, generator=torch.Generator().manual_seed(10))

    def run(g):
        out, rows = g.query(x, 0.43, 1, track=True)
        (out * w).sum().backward()
        return out.detach(), rows

    (ref, gr), (got, gc) = _both(h, run)
    torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-7)
    assert torch.equal(gc.rows, gr.rows), "the same table rows are touched"
    torch.testing.assert_close(gc.leaf.grad, gr.leaf.grad, rtol=1e-4, atol=1e-5)
    ref_nt, got_nt = _both(h, lambda g: g.query(x, 0.43, 1, track=False)[0])
    torch.testing.assert_close(got_nt, ref_nt, rtol=1e-5, atol=1e-7)


def test_compiled_spatial_grid_matches_torch_values_rows_and_gradients():
    s = SpatialGrid(7, 5)
    s.table = torch.randn(s.table.shape, generator=torch.Generator().manual_seed(11))
    x = _points(4000, 12)
    w = torch.randn(4000, 5, generator=torch.Generator().manual_seed(13))

    def run(g):
        out, rows = g.query(x, track=True)
        (out * w).sum().backward()
        return out.detach(), rows

    (ref, gr), (got, gc) = _both(s, run)
    torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-6)
    assert float(got[3].abs().max()) == 0.0, "a point outside the box gets zero features"
    assert torch.equal(gc.rows, gr.rows)
    torch.testing.assert_close(gc.leaf.grad, gr.leaf.grad, rtol=1e-4, atol=1e-5)


def test_compiled_grid_gradient_matches_finite_differences_in_float32():
    h = HashGrid4D(1, levels=2, features=2, log2_table=6, base_res=2, growth=2.0, max_time_res=2,
                   generator=torch.Generator().manual_seed(14))
    x = _points(7, 15)
    wts = torch.randn(7, 4, generator=torch.Generator().manual_seed(16))
    out, g = h.query(x, 0.6, 0, track=True)
    (out * wts).sum().backward()
    eps = 1e-2  # the output is linear in the table: a large step is exact up to float32 round-off
    for k in range(g.rows.numel()):
        row = int(g.rows[k])
        saved = h.table.clone()
        h.table[row, 1] += eps
        op, _ = h.query(x, 0.6, 0, track=False)
        h.table = saved.clone()
        h.table[row, 1] -= eps
        om, _ = h.query(x, 0.6, 0, track=False)
        h.table = saved
        fd = float(((op - om) * wts).sum()) / (2 * eps)
        assert g.leaf.grad[k, 1].item() == pytest.approx(fd, rel=1e-3, abs=1e-4)


def test_compiled_grids_read_nan_positions_as_zero_instead_of_crashing():
    h = HashGrid4D(1, levels=3, features=2, log2_table=6, base_res=2, growth=2.0, max_time_res=2)
    x = torch.tensor([[float("nan"), 0.5, 0.5], [0.0, 0.5, 0.5]])
    out, g = h.query(x, 0.2, 0, track=True)
    out.sum().backward()
    torch.testing.assert_close(out[0], out[1])
