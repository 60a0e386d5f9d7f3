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


def _compiled_and_reference(tables: dict[str, torch.Tensor]) -> tuple[SparseAdam, SparseAdam, dict, dict]:
    fast_tables = {n: t.clone() for n, t in tables.items()}
    ref_tables = {n: t.clone() for n, t in tables.items()}
    fast, ref = SparseAdam(fast_tables, eps=1e-15), SparseAdam(ref_tables, eps=1e-15, backend="torch")
    assert fast._kernel is not None, "the compiled sparse Adam step builds on this machine"
    return fast, ref, fast_tables, ref_tables


@pytest.mark.parametrize("clip", [0.0, 0.5, 1e6])
def test_compiled_sparse_adam_matches_the_torch_version(clip: float) -> None:
    # tables of the model's shapes (anchor rows, hash rows of 2 features, a per-segment MLP), rows
    # drawn anew each step so that step counts differ per row, scalar and per-row learning rates,
    # non-finite gradient entries, and a clip that is active (0.5) or not (1e6)
    gen = torch.Generator().manual_seed(3)
    tables = {"anchor": torch.randn(300, 48, generator=gen), "hash": torch.randn(5000, 2, generator=gen),
              "mlp": torch.randn(2, 24, 64, generator=gen)}
    fast, ref, fast_tables, ref_tables = _compiled_and_reference(tables)
    for step in range(12):
        for name, table in tables.items():
            n = table.shape[0]
            rows = torch.randperm(n, generator=gen)[: max(1, n // 3)]  # unique, unsorted
            grad = torch.randn((len(rows),) + tuple(table.shape[1:]), generator=gen)
            if step % 4 == 1:
                grad.view(-1)[:3] = torch.tensor([float("nan"), float("inf"), -float("inf")])
            lr = 0.01 if step % 2 else torch.rand(len(rows), generator=gen) * 0.02
            fast.step(name, fast_tables[name], rows, grad, lr, clip=clip)
            ref.step(name, ref_tables[name], rows, grad, lr, clip=clip)
    for name in tables:
        torch.testing.assert_close(fast_tables[name], ref_tables[name], rtol=2e-5, atol=2e-6)
        torch.testing.assert_close(fast.exp_avg[name], ref.exp_avg[name], rtol=2e-5, atol=1e-7)
        torch.testing.assert_close(fast.exp_avg_sq[name], ref.exp_avg_sq[name], rtol=2e-5, atol=1e-9)
        assert torch.equal(fast.steps[name], ref.steps[name])
        assert torch.isfinite(fast_tables[name]).all()
        assert not torch.equal(fast_tables[name], tables[name]), "the step changed the table"


def test_compiled_sparse_adam_clips_to_the_norm() -> None:
    # with a constant gradient Adam's first step moves each entry by lr * sign(g), whatever the
    # scale: the clip is seen in the moments instead (m = (1 - b1) * g * clip / |g|)
    table = torch.zeros(4, 3)
    fast, ref, fast_tables, ref_tables = _compiled_and_reference({"t": table})
    grad = torch.full((2, 3), 2.0)  # norm sqrt(24)
    for opt, tabs in ((fast, fast_tables), (ref, ref_tables)):
        opt.step("t", tabs["t"], torch.tensor([3, 0]), grad, 0.1, clip=1.0)
        expected_m = 0.1 * 2.0 / math.sqrt(24.0)
        assert opt.exp_avg["t"][[0, 3]].flatten().tolist() == pytest.approx([expected_m] * 6, rel=1e-6)
        assert opt.exp_avg["t"][[1, 2]].abs().sum() == 0
        assert tabs["t"][[0, 3]].flatten().tolist() == pytest.approx([-0.1] * 6, rel=1e-5)


def test_compiled_sparse_adam_refuses_rows_outside_the_table() -> None:
    fast, _, fast_tables, _ = _compiled_and_reference({"t": torch.zeros(4, 2)})
    with pytest.raises(RuntimeError, match="out of range"):
        fast.step("t", fast_tables["t"], torch.tensor([1, 4]), torch.ones(2, 2), 0.1)
    assert fast.steps["t"].tolist() == [0, 0, 0, 0], "nothing was written"


def test_sparse_adam_unknown_backend_is_refused() -> None:
    with pytest.raises(ValueError, match="backend"):
        SparseAdam({"t": torch.zeros(2, 2)}, backend="fast")
