"""bench/_harness.py, the Trainer every training bench builds: overrides reach the fields they
name (or fail), a run starts in an empty folder with evaluations and checkpoints off, and the
timed run and steps report what ran. No benchmark runs here: the toy scene and the tiny preset."""

from __future__ import annotations

import ast
import importlib.util
import sys
from pathlib import Path

import pytest

from atgs.train.config import preset
from builders import make_toy_scene

REPO = Path(__file__).resolve().parent.parent
BENCH = REPO / "bench"


def bench_module(name: str, monkeypatch: pytest.MonkeyPatch):
    """bench/<name>.py as a module (it imports its bench/ neighbours)."""
    monkeypatch.syspath_prepend(str(BENCH))
    spec = importlib.util.spec_from_file_location(name, BENCH / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, name, module)  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


@pytest.fixture
def harness(monkeypatch: pytest.MonkeyPatch):
    return bench_module("_harness", monkeypatch)


def read(cfg, key: str):
    for name in key.split("."):
        cfg = getattr(cfg, name)
    return cfg


def flat(overrides: dict, prefix: str = "") -> dict:
    """{"hash": {"levels": 8}} -> {"hash.levels": 8}."""
    out = {}
    for k, v in overrides.items():
        out.update(flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def test_overrides_reach_nested_fields_and_a_typo_fails(harness) -> None:
    m, t = harness.case_configs("cpu", iterations=300, model={"hash": {"log2_table_size": 12}, "window": 3},
                                train={"densify.grad_threshold": 1e-4, "lr": {"temporal_init": 5e-4}}, threads=2)
    ref_m, ref_t = preset("cpu", 300)
    ref_m.hash.log2_table_size, ref_m.window = 12, 3
    ref_t.densify.grad_threshold, ref_t.lr.temporal_init = 1e-4, 5e-4
    ref_t.eval_every = ref_t.save_every = 0
    ref_t.threads = 2
    assert (m, t) == (ref_m, ref_t)
    assert preset("cpu", 300)[0].hash.log2_table_size != 12  # the preset itself is untouched
    with pytest.raises(ValueError, match="densify.grad_treshold"):
        harness.case_configs("cpu", train={"densify.grad_treshold": 1e-4})
    with pytest.raises(ValueError, match="no field 'levles'"):
        harness.case_configs("cpu", model={"hash": {"levles": 4}})


def test_every_bench_case_sets_the_fields_it_names(harness, monkeypatch) -> None:
    knobs = bench_module("budget_knobs", monkeypatch)
    for name, (_, model, train) in knobs.CASES.items():
        m, t = harness.case_configs("cpu", minutes=8, model=model, train=train)
        for cfg, over in ((m, model), (t, train)):
            assert all(read(cfg, k) == v for k, v in flat(over).items()), name
    big = harness.case_configs("cpu", model=knobs.CASES["w7-motion-large"][1])[0]
    assert big.hash.levels == preset("cpu-accurate")[0].hash.levels != preset("cpu")[0].hash.levels

    short = bench_module("short_runs", monkeypatch)
    base_lr = preset("cpu", minutes=8)[1].lr
    for name, over in short.CASES.items():
        _, t = harness.case_configs("cpu", minutes=8, train=short.train_overrides(name, 8))
        for key, value in over.items():  # "lr.x" is a factor of the preset's rate
            want = value * read(base_lr, key[3:]) if key.startswith("lr.") else value
            assert read(t, key) == pytest.approx(want), (name, key)

    moving = bench_module("moving", monkeypatch)
    for name, (_, model) in moving.CASES.items():
        m, _ = harness.case_configs("cpu-fast", iterations=100, model=model)
        assert all(read(m, k) == v for k, v in model.items()), name

    tradeoff = bench_module("tradeoff", monkeypatch)
    specs = tradeoff.plan(tradeoff.TradeoffArgs())
    assert {s.group for s in specs} == set(tradeoff.GROUPS)
    for s in specs:
        m, t = harness.case_configs(s.preset, iterations=s.iterations, model=s.model_overrides,
                                    train=s.train_overrides)
        assert all(read(m, k) == v for k, v in s.model_overrides.items()), s.name
        assert all(read(t, k) == v for k, v in s.train_overrides.items()), s.name


def test_a_bench_trainer_starts_empty_and_its_timed_run_reports_what_ran(harness, tmp_path) -> None:
    scene = make_toy_scene(num_frames=4, num_cameras=4, width=32, height=24, keyframes=2)
    out = tmp_path / "run"
    out.mkdir()
    (out / "eval").mkdir()
    (out / "eval" / "stale.png").write_bytes(b"an earlier run's image")
    tr = harness.build_trainer(scene, out, "tiny", iterations=3, train={"seed": 1}, threads=1)
    assert not (out / "eval").exists()
    assert (tr.cfg.eval_every, tr.cfg.save_every, tr.cfg.seed, tr.cfg.iterations) == (0, 0, 1, 3)

    results, seconds = harness.timed_steps(tr, 2)
    assert len(results) == 2 and tr.step == 2 and seconds > 0

    timed = harness.run_timed(tr)  # the default: held-out scores after the timed steps
    assert tr.step == 3 and timed.seconds > 0 and (out / "ckpt.pt").is_file()
    assert timed.eval["views"] == tr.final_views() and 0 < timed.eval["psnr"] < 100
    assert not (out / "eval").exists()  # scores only: no images written

    untimed = harness.build_trainer(scene, out, "tiny", iterations=2)
    assert not (out / "ckpt.pt").exists()
    assert "eval" not in harness.run_timed(untimed, "none").result
    with pytest.raises(ValueError, match="final='all'"):
        harness.run_timed(untimed, "all")


def test_only_the_harness_constructs_a_trainer_in_bench() -> None:
    """Every bench builds its Trainer through bench/_harness.py's build_trainer."""
    callers = []
    for path in sorted(BENCH.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Call) and getattr(node.func, "id", getattr(node.func, "attr", None)) == "Trainer":
                callers.append(path.name)
    assert callers == ["_harness.py"]
