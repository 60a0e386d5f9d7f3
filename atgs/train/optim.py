"""Row-sparse ("lazy") Adam for large tables.

Only the rows given to :meth:`SparseAdam.step` are read and written. Each row keeps its own step
count, so bias correction is exact for rows that are touched rarely (hash-table rows, anchors
of rarely visited keyframes); for rows touched every step this is exactly dense Adam.

On the CPU, float32 tables are updated by a compiled kernel (atgs/render/csrc/sparse_adam.cpp,
built on first use like the rasterizer) that reads and writes each row once; the torch code here
is its reference and the path for other devices and dtypes (``backend="torch"`` forces it).
"""

from __future__ import annotations

import torch

OPTIM_BACKENDS = ("auto", "torch")
_NO_LR = torch.empty(0, dtype=torch.float32, device="cpu")  # the compiled step's "one learning rate for all rows"


def merge_rows(parts: list[tuple[torch.Tensor, torch.Tensor]]) -> tuple[torch.Tensor, torch.Tensor]:
    """One table's gradient from several (rows, grad) parts (views of a step, or workers): the
    union of the rows, each with the sum of its parts' gradients in the order given. Rows are
    unique within a part; a single part is returned as it is."""
    if len(parts) == 1:
        return parts[0]
    rows, inv = torch.unique(torch.cat([r for r, _ in parts]), return_inverse=True)
    g = parts[0][1].new_zeros((rows.numel(),) + tuple(parts[0][1].shape[1:]))
    g.index_add_(0, inv, torch.cat([x for _, x in parts]))
    return rows, g


def _compiled_kernel():
    """The compiled step, or None where it does not build (the torch version then serves)."""
    from atgs.render.build import SPARSE_ADAM, cpu_backend_error, load_extension

    return None if cpu_backend_error(SPARSE_ADAM) else load_extension(SPARSE_ADAM)


def _taken_over(saved: dict[str, torch.Tensor], tables: dict[str, torch.Tensor], key: str) -> dict[str, torch.Tensor]:
    """A saved store of moments or step counts, one per table, on the tables' devices; zeros
    for a table the store lacks (a new optimizer, or a checkpoint from before that table)."""
    unknown = sorted(set(saved) - set(tables))
    if unknown:
        raise ValueError(f"optimizer state has unknown tables {unknown}")
    out = {}
    for name, t in tables.items():
        if name not in saved:
            out[name] = torch.zeros_like(t) if key != "steps" else torch.zeros(
                t.shape[0], dtype=torch.int64, device=t.device)
            continue
        if saved[name].shape[0] != t.shape[0]:
            raise ValueError(f"optimizer state {key}/{name} has {saved[name].shape[0]} rows, the table {t.shape[0]}")
        out[name] = saved[name].to(t.device).contiguous()
    return out


class SparseAdam:
    STORES = ("exp_avg", "exp_avg_sq", "steps")  # per table: a row each (the state's layout)

    def __init__(self, tables: dict[str, torch.Tensor], betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-15, backend: str = "auto", state: dict | None = None) -> None:
        """``state``: a saved :meth:`state_dict` of these tables to continue from, taken over
        (moved to the tables' devices, not copied: a resumed run never holds it twice); None:
        zero moments."""
        if backend not in OPTIM_BACKENDS:
            raise ValueError(f"SparseAdam backend must be one of {OPTIM_BACKENDS}, got {backend!r}")
        self.betas, self.eps, self.backend = betas, eps, backend
        for key in self.STORES:
            setattr(self, key, _taken_over({} if state is None else state[key], tables, key))
        # build the kernel now (seconds, once per version), not inside a time-budgeted step
        self._kernel = _compiled_kernel() if backend == "auto" and any(
            t.device.type == "cpu" and t.dtype == torch.float32 for t in tables.values()) else None

    def _compiled_for(self, name: str, table: torch.Tensor, grad: torch.Tensor, lr) -> bool:
        if self._kernel is None or self.backend == "torch":
            return False
        tensors = (table, grad, self.exp_avg[name], self.exp_avg_sq[name])
        return (all(t.device.type == "cpu" and t.dtype == torch.float32 and t.is_contiguous() for t in tensors)
                and (not isinstance(lr, torch.Tensor) or lr.device.type == "cpu"))

    def step(self, name: str, table: torch.Tensor, rows: torch.Tensor, grad: torch.Tensor,
             lr: float | torch.Tensor, clip: float = 0.0) -> None:
        """Adam update of ``table[rows]`` in place with gradient ``grad`` (len(rows), ...).
        ``rows`` must be unique; ``lr`` is a float or one learning rate per row. Non-finite
        gradient entries count as 0; with ``clip`` > 0 the gradient is first scaled to that norm
        when above it."""
        if rows.numel() == 0:
            return
        if self._compiled_for(name, table, grad, lr):
            lr_rows = lr.float().contiguous() if isinstance(lr, torch.Tensor) else _NO_LR
            self._kernel.step(table, self.exp_avg[name], self.exp_avg_sq[name], self.steps[name],
                              rows.long().contiguous(), grad.contiguous(), lr_rows,
                              0.0 if isinstance(lr, torch.Tensor) else float(lr),
                              self.betas[0], self.betas[1], float(self.eps), float(clip), torch.get_num_threads())
            return
        self.step_reference(name, table, rows, grad, lr, clip)

    def step_reference(self, name: str, table: torch.Tensor, rows: torch.Tensor, grad: torch.Tensor,
                       lr: float | torch.Tensor, clip: float = 0.0) -> None:
        """:meth:`step` in torch ops (any device and dtype; the compiled kernel's reference)."""
        if rows.numel() == 0:
            return
        grad = torch.nan_to_num(grad, nan=0.0, posinf=0.0, neginf=0.0)
        if clip > 0:  # on the device, without reading the norm back (float64 as Python's)
            norm = grad.norm().double()
            grad = grad * torch.where(norm > clip, clip / norm, 1.0).to(grad.dtype)
        b1, b2 = self.betas
        m = self.exp_avg[name].index_select(0, rows)
        v = self.exp_avg_sq[name].index_select(0, rows)
        n = self.steps[name].index_select(0, rows) + 1
        m.mul_(b1).add_(grad, alpha=1 - b1)
        v.mul_(b2).addcmul_(grad, grad, value=1 - b2)
        shape = (-1,) + (1,) * (grad.dim() - 1)
        bc1 = (1 - b1 ** n.double()).to(grad.dtype).view(shape)
        bc2 = (1 - b2 ** n.double()).to(grad.dtype).view(shape)
        update = (m / bc1) / ((v / bc2).sqrt() + self.eps)
        if isinstance(lr, torch.Tensor):
            lr = lr.to(update.dtype).view(shape)
        table.index_copy_(0, rows, table.index_select(0, rows) - lr * update)
        self.exp_avg[name].index_copy_(0, rows, m)
        self.exp_avg_sq[name].index_copy_(0, rows, v)
        self.steps[name].index_copy_(0, rows, n)

    # --- rows appended / removed (anchor growing and pruning) ------------------------------------
    def append_rows(self, name: str, n: int) -> None:
        for store in (self.exp_avg, self.exp_avg_sq):
            t = store[name]
            store[name] = torch.cat([t, t.new_zeros((n,) + tuple(t.shape[1:]))])
        self.steps[name] = torch.cat([self.steps[name], self.steps[name].new_zeros(n)])

    def keep_rows(self, name: str, keep: torch.Tensor) -> None:
        for store in (self.exp_avg, self.exp_avg_sq, self.steps):
            store[name] = store[name][keep].contiguous()

    def state_dict(self) -> dict:
        return {key: dict(getattr(self, key)) for key in self.STORES}

    # --- rows of the state (several workers: a worker's share, a checkpoint's pieces) -----------
    def rows_from(self, name: str, first: int) -> dict[str, torch.Tensor]:
        """Table ``name``'s state from row ``first`` on, by :meth:`state_dict` key."""
        return {key: getattr(self, key)[name][first:] for key in self.STORES}

    @classmethod
    def state_paths(cls, name: str) -> list[tuple[str, str]]:
        """Where table ``name``'s rows are in a :meth:`state_dict`."""
        return [(key, name) for key in cls.STORES]

    @classmethod
    def rows_of_state(cls, state: dict, names: "set[str] | tuple[str, ...]", ids: torch.Tensor) -> dict:
        """A :meth:`state_dict` with only the rows ``ids`` of the tables ``names`` (the others whole)."""
        ids = ids.cpu()
        return {key: {name: (rows[ids.to(rows.device)].contiguous() if name in names else rows)
                      for name, rows in state[key].items()} for key in cls.STORES}
