"""Feature grids in pure PyTorch: the dense spatial grid F_s (trilinear) and the 4D
multi-resolution hash grids F_T,m (Instant-NGP style, quadrilinear).

Both are gather based: a query computes integer row indices into a 2D table (rows, features)
and interpolation weights. :func:`gather_rows` turns the table rows touched by a query into a
small leaf tensor, so that backward produces a gradient for the touched rows only (an
index_add into a (U, D) tensor) and the optimizer updates only those rows.

On the CPU the same lookups run as compiled kernels (atgs/render/csrc/grids.cpp, several times
faster: no (N, L, 16) index tensors); the torch code here is their reference and the path for
other devices. ``backend`` on a grid picks: "auto" (compiled when on the CPU and the kernels
build) or "torch".
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
import math

import torch

# Instant-NGP spatial hash primes (first dimension uses 1).
_PRIMES = (1, 2654435761, 805459861, 3674653429)


@dataclass
class RowGather:
    """Rows of a table touched by one query; ``leaf.grad`` after backward is their gradient."""

    rows: torch.Tensor  # (U,) int64 unique, ascending
    leaf: torch.Tensor  # (U, D) a copy of table[rows] that requires grad


def gather_rows(table: torch.Tensor, idx: torch.Tensor, track: bool) -> tuple[torch.Tensor, RowGather | None]:
    """``table[idx]`` (shape idx.shape + (D,)); with ``track`` the result depends on a leaf of the
    unique touched rows (found with a mask, no sort of the query indices)."""
    if not track:
        return table[idx], None
    flat = idx.reshape(-1)
    mask = torch.zeros(table.shape[0], dtype=torch.bool, device=table.device)
    mask[flat] = True
    rows = mask.nonzero().squeeze(1)
    remap = torch.empty(table.shape[0], dtype=torch.int64, device=table.device)
    remap[rows] = torch.arange(rows.numel(), device=table.device)
    leaf = table.index_select(0, rows).detach().requires_grad_(True)
    out = leaf[remap[flat]].reshape(*idx.shape, table.shape[1])
    return out, RowGather(rows, leaf)


def grid_kernels(table: torch.Tensor, backend: str):
    """The compiled grid kernels if they should serve a lookup into ``table``, else None (the
    first call builds them: a trainer calls this while it sets up)."""
    if backend not in ("auto", "torch"):
        raise ValueError(f"grid backend must be 'auto' or 'torch', got {backend!r}")
    if backend == "torch" or table.device.type != "cpu" or table.dtype != torch.float32:
        return None
    from atgs.render.build import GRIDS, cpu_backend_error, load_extension

    return None if cpu_backend_error(GRIDS) else load_extension(GRIDS)


_NO_REMAP = torch.empty(0, dtype=torch.int64, device="cpu")  # the compiled kernels run on the CPU


class _CompiledLookup(torch.autograd.Function):
    """out = lookup(table); the gradient goes to ``leaf``, a copy of the table's ``rows``. The
    forward reads the table itself (the same values). The backward scatters through ``remap``
    (table row -> leaf row) into the leaf's gradient, or, without one, into a table-sized
    gradient whose ``rows`` are then read out (csrc/grids.cpp says which suits which grid)."""

    @staticmethod
    def forward(ctx, leaf, table, rows, remap, x, fwd, bwd):  # type: ignore[override]
        ctx.save_for_backward(x, rows, remap)
        ctx.bwd, ctx.table_rows, ctx.leaf_rows = bwd, table.shape[0], leaf.shape[0]
        return fwd(x, table)

    @staticmethod
    def backward(ctx, grad_out):  # type: ignore[override]
        x, rows, remap = ctx.saved_tensors
        if remap.numel():
            grad = ctx.bwd(x, grad_out.contiguous(), ctx.leaf_rows, remap)
        else:
            grad = ctx.bwd(x, grad_out.contiguous(), ctx.table_rows, remap).index_select(0, rows)
        return grad, None, None, None, None, None, None


def compiled_lookup(table: torch.Tensor, x: torch.Tensor, track: bool, touched: Callable, fwd: Callable,
                    bwd: Callable, remap: bool, row_offset: int = 0) -> tuple[torch.Tensor, RowGather | None]:
    """A grid lookup through compiled kernels, with the semantics of :func:`gather_rows` +
    interpolation: with ``track`` the result depends on a leaf of the touched rows. ``remap``:
    the backward scatters into the leaf rows directly (see :class:`_CompiledLookup`).
    ``table`` may be a block of rows of a larger table starting at ``row_offset``: the
    returned rows are then rows of the larger table."""
    x, table = x.detach().float().contiguous(), table.detach().contiguous()
    if not track:
        return fwd(x, table), None
    rows = touched(x).nonzero().squeeze(1)
    leaf = table.index_select(0, rows).detach().requires_grad_(True)
    to_leaf = _NO_REMAP
    if remap:
        to_leaf = torch.full((table.shape[0],), -1, dtype=torch.int64, device=table.device)
        to_leaf[rows] = torch.arange(rows.numel(), device=table.device)
    return _CompiledLookup.apply(leaf, table, rows, to_leaf, x, fwd, bwd), RowGather(rows + row_offset if row_offset else rows, leaf)


def _corner_offsets(dims: int, device: torch.device) -> torch.Tensor:
    """(2^dims, dims) 0/1 offsets of the corners of a unit cell."""
    c = torch.arange(2**dims, device=device)
    return torch.stack([(c >> d) & 1 for d in range(dims)], dim=1)


def interp_indices(x: torch.Tensor, res: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Cell corners and multilinear weights of points x (N, d) in [0, 1]^d on a grid with
    ``res[d] + 1`` vertices along dimension d. Returns corners (N, 2^d, d) int64 and
    weights (N, 2^d)."""
    d = x.shape[1]
    r = torch.tensor(res, dtype=x.dtype, device=x.device)
    pos = x.clamp(0.0, 1.0) * r
    base = torch.minimum(pos.floor(), r - 1).clamp_min(0)
    frac = pos - base
    offs = _corner_offsets(d, x.device)  # (C, d)
    corners = base.long()[:, None, :] + offs[None]
    w = torch.where(offs[None].bool(), frac[:, None, :], 1.0 - frac[:, None, :]).prod(dim=2)
    return corners, w


class SpatialGrid:
    """Dense grid of ``res^3`` vertices x D features over [0, 1]^3, trilinear, zero init."""

    def __init__(self, res: int, dim: int, device: torch.device | str = "cpu", backend: str = "auto") -> None:
        self.res, self.dim = int(res), int(dim)
        self.table = torch.zeros(self.res**3, self.dim, device=device)
        self.backend = backend

    def indices(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        n = self.res - 1
        corners, w = interp_indices(x, [n, n, n])
        idx = corners[..., 0] + self.res * (corners[..., 1] + self.res * corners[..., 2])
        return idx, w

    def query(self, x: torch.Tensor, track: bool) -> tuple[torch.Tensor, RowGather | None]:
        """Features (N, D) of points x (N, 3) in [0, 1]^3; points outside get zeros."""
        inside = ((x >= 0) & (x <= 1)).all(dim=1)
        k = grid_kernels(self.table, self.backend)
        if k is not None:
            t = torch.get_num_threads()
            out, g = compiled_lookup(
                self.table, x, track, lambda p: k.dense_touched(p, self.res, t),
                lambda p, v: k.dense_forward(p, self.res, v, t),
                lambda p, go, n, r: k.dense_backward(p, self.res, go, n, r, t), remap=True)
        else:
            idx, w = self.indices(x)
            feats, g = gather_rows(self.table, idx, track)
            out = (feats * w[..., None]).sum(dim=1)
        return out * inside[:, None].to(out.dtype), g


class HashGrid4D:
    """M independent 4D multi-resolution hash grids stored in one table.

    Table rows: ``((m * L) + level) * T + slot``; level l has spatial resolution
    ``floor(base * growth^l)`` and time resolution ``min(that, max_time_res)``. A level whose
    vertices fit in T slots is indexed densely (no collisions), else hashed.
    """

    def __init__(self, num_grids: int, levels: int, features: int, log2_table: int, base_res: int,
                 growth: float, max_time_res: int, init_scale: float = 1e-4,
                 generator: torch.Generator | None = None, backend: str = "auto",
                 grids: range | None = None, draw: bool = True) -> None:
        """``grids``: keep only these grids' rows (a worker of the time partition,
        atgs.train.partition.time_slice; the generator is still advanced over all of them, one grid's
        draws at a time); the table then holds ``len(grids)`` grids, queried by local index.
        ``draw=False``: leave the table uninitialised (a loaded table replaces it)."""
        self.levels, self.features = int(levels), int(features)
        self.table_size = 2 ** int(log2_table)
        self.res = [max(1, int(math.floor(base_res * growth**lv))) for lv in range(self.levels)]
        self.time_res = [max(1, min(r, int(max_time_res))) for r in self.res]
        # Instant-NGP initializes uniformly in [-1e-4, 1e-4].
        device = generator.device if generator is not None else "cpu"
        if not draw:
            self.num_grids = int(num_grids) if grids is None else len(grids)
            self.table = torch.empty(self.num_grids * self.levels * self.table_size, self.features, device=device)
        elif grids is None:
            self.num_grids = int(num_grids)
            rows = self.num_grids * self.levels * self.table_size
            self.table = (torch.rand(rows, self.features, generator=generator, device=device) * 2 - 1) * init_scale
        else:
            self.num_grids = len(grids)
            per_grid = self.levels * self.table_size
            blocks = []
            for m in range(int(num_grids)):
                block = torch.rand(per_grid, self.features, generator=generator, device=device)
                if m in grids:
                    blocks.append((block * 2 - 1) * init_scale)
            self.table = torch.cat(blocks)
        self.backend = backend

    def dense_level(self, lv: int) -> bool:
        r, rt = self.res[lv], self.time_res[lv]
        return (r + 1) ** 3 * (rt + 1) <= self.table_size

    def level_slots(self, corners: torch.Tensor, lv: int) -> torch.Tensor:
        """Slot in [0, T) of integer 4D vertices (..., 4) at level lv."""
        r = self.res[lv]
        x, y, z, w = corners.unbind(-1)
        if self.dense_level(lv):
            return x + (r + 1) * (y + (r + 1) * (z + (r + 1) * w))
        h = x * _PRIMES[0]
        for c, p in zip((y, z, w), _PRIMES[1:]):
            h = h ^ (c * p)  # int64 wrap-around keeps the low bits exact
        return h & (self.table_size - 1)

    def spatial_slots(self, x: torch.Tensor, lv: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Time-invariant part of level lv for points x (N, 3): partial slots (N, 8) int64 and
        trilinear weights (N, 8). :meth:`combine_time` adds a time vertex; the result equals
        :meth:`level_slots` of the 4D corner (both the dense sum and the hash xor split exactly)."""
        r = self.res[lv]
        corners, w = interp_indices(x.clamp(0, 1), [r, r, r])
        cx, cy, cz = corners.unbind(-1)
        if self.dense_level(lv):
            return cx + (r + 1) * (cy + (r + 1) * cz), w
        h = cx * _PRIMES[0]
        for c, p in zip((cy, cz), _PRIMES[1:3]):
            h = h ^ (c * p)
        return h & (self.table_size - 1), w  # (a ^ b) & m == (a & m) ^ (b & m)

    def combine_time(self, partial: torch.Tensor, lv: int, vertex: int, grid: int) -> torch.Tensor:
        """Table rows of the spatial partial slots of level lv at integer time vertex ``vertex``."""
        r = self.res[lv]
        if self.dense_level(lv):
            slots = partial + (r + 1) ** 3 * vertex
        else:
            slots = partial ^ ((vertex * _PRIMES[3]) & (self.table_size - 1))
        return slots + (grid * self.levels + lv) * self.table_size

    def time_corners(self, tau: float, lv: int) -> tuple[int, float, float]:
        """(lower time vertex, weight of it, weight of the next one) of local time tau at level lv,
        computed in float32 exactly as :func:`interp_indices` does for the 4th coordinate."""
        # a few host scalars: returned as Python numbers, no device round trip
        t = torch.full((1, 1), float(tau), dtype=torch.float32, device="cpu").clamp(0, 1)
        corners, w = interp_indices(t, [self.time_res[lv]])
        return int(corners[0, 0, 0]), float(w[0, 0]), float(w[0, 1])

    def indices(self, x: torch.Tensor, tau: float, grid: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Rows (N, L, 16) and weights (N, L, 16) of points x (N, 3) in [0,1]^3 at local time tau."""
        n = x.shape[0]
        x4 = torch.cat([x.clamp(0, 1), torch.full((n, 1), float(tau), dtype=x.dtype, device=x.device).clamp(0, 1)],
                       dim=1)
        all_idx, all_w = [], []
        for lv in range(self.levels):
            r, rt = self.res[lv], self.time_res[lv]
            corners, w = interp_indices(x4, [r, r, r, rt])
            slots = self.level_slots(corners, lv)
            all_idx.append(slots + (grid * self.levels + lv) * self.table_size)
            all_w.append(w)
        return torch.stack(all_idx, dim=1), torch.stack(all_w, dim=1)

    def query(self, x: torch.Tensor, tau: float, grid: int, track: bool) -> tuple[torch.Tensor, RowGather | None]:
        """Concatenated level features (N, L*F)."""
        k = grid_kernels(self.table, self.backend)
        if k is not None:
            dense = [int(self.dense_level(lv)) for lv in range(self.levels)]
            # only grid ``grid``'s rows (one block of the table) go to the kernels, as grid 0: the
            # touched mask and the backward's table-sized gradient then cover 1/M of the table
            per_grid = self.levels * self.table_size
            block = self.table[grid * per_grid:(grid + 1) * per_grid]
            args = (float(tau), 0, self.res, self.time_res, dense, self.table_size)
            t = torch.get_num_threads()
            return compiled_lookup(
                block, x, track, lambda p: k.hash_touched(p, *args, per_grid, t),
                lambda p, v: k.hash_forward(p, *args, v, t),
                lambda p, go, n, r: k.hash_backward(p, *args, go, n, r, t), remap=False,
                row_offset=grid * per_grid)
        idx, w = self.indices(x, tau, grid)
        feats, g = gather_rows(self.table, idx, track)  # (N, L, 16, F)
        out = (feats * w[..., None]).sum(dim=2)
        return out.reshape(x.shape[0], self.levels * self.features), g
