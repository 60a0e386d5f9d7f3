"""Row-sparse ("lazy") Adam for large tables.

Only the rows given to :meth:`SparseAdam.step` are read and written. Each row keeps its own step
count, so bias correction is exact for rows that are touched rarely (hash-table rows, anchors
of rarely visited keyframes); for rows touched every step this is exactly dense Adam.
"""

from __future__ import annotations

import torch


class SparseAdam:
    def __init__(self, tables: dict[str, torch.Tensor], betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-15) -> None:
        self.betas, self.eps = betas, eps
        self.exp_avg = {n: torch.zeros_like(t) for n, t in tables.items()}
        self.exp_avg_sq = {n: torch.zeros_like(t) for n, t in tables.items()}
        self.steps = {n: torch.zeros(t.shape[0], dtype=torch.int64, device=t.device) for n, t in tables.items()}

    def step(self, name: str, table: torch.Tensor, rows: torch.Tensor, grad: torch.Tensor,
             lr: float | torch.Tensor) -> None:
        """Adam update of ``table[rows]`` in place with gradient ``grad`` (len(rows), ...).
        ``rows`` must be unique; ``lr`` is a float or one learning rate per row."""
        if rows.numel() == 0:
            return
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
        return {"exp_avg": dict(self.exp_avg), "exp_avg_sq": dict(self.exp_avg_sq), "steps": dict(self.steps)}

    def load_state_dict(self, state: dict) -> None:
        """Load a state saved on any device onto the device of this optimizer's tables."""
        for key in ("exp_avg", "exp_avg_sq", "steps"):
            mine = getattr(self, key)
            for name, value in state[key].items():
                if name not in mine:
                    raise ValueError(f"optimizer state has unknown table {name!r}")
                mine[name] = value.to(mine[name].device, copy=True)
