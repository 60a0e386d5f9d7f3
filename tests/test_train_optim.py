"""SparseAdam vs torch.optim.Adam; schedules."""

import math

import pytest
import torch

from atgs.train.optim import SparseAdam
from atgs.train.schedule import exp_decay, warmup


def _grads(step: int, shape) -> torch.Tensor:
    return torch.randn(shape, generator=torch.Generator().manual_seed(100 + step), dtype=torch.float64)


def test_sparse_adam_equals_dense_adam_on_rows_touched_every_step():
    gen = torch.Generator().manual_seed(0)
    table = torch.randn(50, 4, generator=gen, dtype=torch.float64)
    rows = torch.tensor([2, 5, 11, 30, 49])
    ref = table[rows].clone().requires_grad_(True)
    dense = torch.optim.Adam([ref], lr=0.01, eps=1e-15)
    opt = SparseAdam({"t": table}, eps=1e-15)
    untouched = table.clone()
    for step in range(25):
        g = _grads(step, (5, 4))
        ref.grad = g.clone()
        dense.step()
        opt.step("t", table, rows, g, 0.01)
    torch.testing.assert_close(table[rows], ref.detach(), rtol=1e-12, atol=1e-12)
    mask = torch.ones(50, dtype=torch.bool)
    mask[rows] = False
    assert torch.equal(table[mask], untouched[mask]), "untouched rows never change"


def test_sparse_adam_per_row_step_counts_and_lr():
    table = torch.zeros(3, 2, dtype=torch.float64)
    opt = SparseAdam({"t": table}, eps=1e-15)
    opt.step("t", table, torch.tensor([0]), torch.ones(1, 2, dtype=torch.float64), 0.1)
    opt.step("t", table, torch.tensor([0, 2]), torch.ones(2, 2, dtype=torch.float64),
             torch.tensor([0.1, 0.5]))
    # with a constant gradient every Adam step moves by exactly lr (bias-corrected)
    assert table[0].tolist() == pytest.approx([-0.2, -0.2])
    assert table[2].tolist() == pytest.approx([-0.5, -0.5])
    assert table[1].tolist() == [0.0, 0.0]
    assert opt.steps["t"].tolist() == [2, 0, 1]


def test_sparse_adam_rows_append_and_keep():
    table = torch.zeros(3, 2)
    opt = SparseAdam({"t": table})
    opt.step("t", table, torch.tensor([1]), torch.ones(1, 2), 0.1)
    opt.append_rows("t", 2)
    assert opt.exp_avg["t"].shape == (5, 2) and opt.steps["t"].tolist() == [0, 1, 0, 0, 0]
    opt.keep_rows("t", torch.tensor([False, True, False, True, True]))
    assert opt.steps["t"].tolist() == [1, 0, 0]
    assert opt.exp_avg["t"][0].tolist() == pytest.approx([0.1, 0.1])


def test_schedules():
    assert exp_decay(1e-2, 1e-4, 0, 100) == pytest.approx(1e-2)
    assert exp_decay(1e-2, 1e-4, 50, 100) == pytest.approx(1e-3)
    assert exp_decay(1e-2, 1e-4, 500, 100) == pytest.approx(1e-4)
    assert warmup(0, 10, 0.1) == pytest.approx(0.1)
    assert warmup(5, 10, 0.1) == pytest.approx(0.55)
    assert warmup(10, 10, 0.1) == 1.0 and warmup(3, 0, 0.1) == 1.0
    assert math.isclose(exp_decay(4e-3, 4e-3, 7, 10), 4e-3)
