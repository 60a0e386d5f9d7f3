"""--minutes: the step count follows the measured pace, the schedule stretches with it, the run
ends on time, and a resumed run counts the time already used. Time is simulated (a fake clock),
so nothing here depends on the machine's speed."""

from __future__ import annotations

import dataclasses
import time

import pytest
import torch

from atgs.cli.train import main as train_main
from atgs.train.budget import FREEZE_FRACTION, TimeBudget
from atgs.train.config import preset
from atgs.train.step_schedule import schedule_for, schedule_of
from atgs.train.trainer import Trainer
from builders import make_toy_scene


def simulate(budget: TimeBudget, pace_of_step, planned: int, step: int = 0, used: float = 0.0
             ) -> tuple[int, float, list[int]]:
    """Run the planning loop with a clock that advances pace_of_step(step) per step (from ``step``
    steps done in ``used`` seconds)."""
    plans = []
    while step < planned:
        used += pace_of_step(step)
        step += 1
        n = budget.plan(step, used, planned)
        if n is not None:
            planned = n
            plans.append(n)
    return step, used, plans


@pytest.mark.parametrize("profile", ["constant", "doubles", "halves", "jump"])
def test_the_plan_ends_on_time_for_any_pace(profile: str) -> None:
    seconds = 600.0
    paces = {"constant": lambda s: 0.2,
             "doubles": lambda s: 0.2 * (1 + min(s, 1500) / 1500),  # the model grows during densification
             "halves": lambda s: 0.4 / (1 + min(s, 1500) / 1500),
             "jump": lambda s: 0.2 if s < 800 else 0.5}
    b = TimeBudget(seconds)
    steps, used, plans = simulate(b, paces[profile], 5000)
    reserve = b.reserve()
    assert plans, "the first plan replaces the preset's step count"
    assert used <= seconds - reserve + 2 * max(paces[profile](s) for s in range(steps)), "ends on time"
    # uses the time: at worst the steps after the last re-sizing ran faster than planned
    assert used >= (1 - (1 - FREEZE_FRACTION) * 0.55) * (seconds - reserve) - 5.0, (used, steps)
    if profile == "constant":
        assert abs(steps - (seconds - reserve) / 0.2) <= 10


def test_a_slow_patch_does_not_end_the_run() -> None:
    """Another job took the machine for 40 steps late in a 20-minute run whose final evaluation
    renders 480 views: sized by the patch's pace, the reserve (480 steps at 2 s) swallowed the
    time left, the plan shrank to the step it was at and froze there (ended after 229 s of 1200).
    Sized by the run's mean pace, the run goes on and uses its budget."""
    def pace(s: int) -> float:
        return 2.0 if 380 <= s < 420 else 0.25
    b = TimeBudget(1200.0, reserve_views=480)
    steps, used, _ = simulate(b, pace, 5000)
    assert used >= 0.8 * (1200.0 - b.reserve()), (steps, used, b.reserve())
    assert used <= 1200.0 - b.reserve() + 2 * 2.0


def test_out_of_time_ends_at_once() -> None:
    b = TimeBudget(10.0)
    steps, used, _ = simulate(b, lambda s: 0.2 if s < 30 else 5.0, 5000)  # suddenly 25x slower
    assert used <= 10.0 + 5.0 and steps == 31  # the step that crossed the limit is the last


def test_the_schedule_is_sized_from_the_step_count_and_never_drifts() -> None:
    """Each re-sizing starts from the rule, not from the last re-sizing, so rounding never drifts;
    what the step count does not size stays the preset's."""
    _, cfg = preset("cpu")
    for n in (777, 12_345, 5000, 3):
        cfg = schedule_for(cfg, n)
    assert cfg.iterations == 3 and cfg.densify.start >= 1 and cfg.densify.interval >= 1
    cfg = schedule_for(cfg, 10_000)
    assert schedule_of(cfg) == schedule_of(preset("cpu", iterations=10_000)[1])
    # the rule of the CPU presets (docs/training.md): densify from N/20 every N/60 steps, warm up
    # over N/30, evaluate every N/4 and save every N/6 steps, above their floors
    assert (cfg.iterations, cfg.densify.start, cfg.densify.interval, cfg.lr.warmup_steps, cfg.eval_every,
            cfg.save_every) == (10_000, 10_000 // 20, 10_000 // 60, 10_000 // 30, 10_000 // 4, 10_000 // 6)
    assert cfg.densify.stop_fraction == preset("cpu")[1].densify.stop_fraction


def _budget_trainer(scene, out, minutes: float) -> Trainer:
    m, t = preset("tiny")
    # the simulated clock covers the steps only: no real set-up time (the scene flow) in the budget
    t = dataclasses.replace(t, minutes=minutes, iterations=40, eval_every=0, save_every=0, velocity_from_flow=False)
    tr = Trainer(scene, m, t, out)
    tr.clock = lambda: 0.5 * tr.step  # every step takes half a second
    return tr


def test_the_scene_flow_set_up_is_paid_from_the_budget(tmp_path, monkeypatch) -> None:
    """Starting the anchors' velocities from optical flow takes set-up time (tens of seconds on the
    built-in scene): a --minutes budget counts it as used before the first step."""
    import atgs.train.scene_setup as scene_setup

    real = scene_setup.initial_velocities

    def slow(*args, **kwargs):
        time.sleep(0.3)
        return real(*args, **kwargs)

    monkeypatch.setattr(scene_setup, "initial_velocities", slow)
    scene = make_toy_scene(num_frames=6, num_cameras=4, width=32, height=24, keyframes=3)
    m, t = preset("tiny")
    on = Trainer(scene, m, dataclasses.replace(t, minutes=1.0), tmp_path / "on")
    off = Trainer(scene, m, dataclasses.replace(t, minutes=1.0, velocity_from_flow=False), tmp_path / "off")
    assert on.scene_flow_stats is not None and on.budget.used >= 0.3
    assert off.scene_flow_stats is None and off.budget.used == 0.0


def test_trainer_fills_the_budget_and_resume_counts_the_time_used(tmp_path) -> None:
    scene = make_toy_scene(num_frames=6, num_cameras=4, width=32, height=24, keyframes=3)
    tr = _budget_trainer(scene, tmp_path / "run", minutes=0.5)
    res = tr.run_steps(progress=False)
    reserve = tr.budget.reserve()
    assert res["seconds_per_step"] == pytest.approx(0.5)
    assert abs(tr.step - (30.0 - reserve) / 0.5) <= 2, (tr.step, reserve)  # not the preset's 40 steps
    assert tr.cfg.iterations == tr.step and res["seconds_used"] == pytest.approx(0.5 * tr.step)
    assert tr.cfg.densify.interval == schedule_for(preset("tiny")[1], tr.step).densify.interval
    ck = torch.load(tmp_path / "run" / "ckpt.pt", weights_only=True)
    assert ck["trainer"]["budget"]["used"] == pytest.approx(0.5 * tr.step)
    assert ck["train_config"]["minutes"] == 0.5

    # resume with a 1-minute total: the half minute already used counts
    tr2 = Trainer.resume(scene, tmp_path / "run" / "ckpt.pt", tmp_path / "run", minutes=1.0)
    start = tr2.step
    tr2.clock = lambda: 0.5 * (tr2.step - start)
    tr2.run_steps(progress=False)
    total = tr2.budget.used + 0.5 * (tr2.step - start)
    assert 50.0 <= total <= 60.0 and tr2.step > start + 45


def test_the_rasterizer_compiles_in_set_up_not_in_the_budget(tmp_path, monkeypatch) -> None:
    """gsplat compiles its CUDA kernels on its first rasterization (56 s on 16 cores, minutes on
    a laptop): a first step doing it would spend the budget. The trainer renders one Gaussian
    forward and backward while it sets up, on its device and backend, before the clock starts."""
    import atgs.render.api as api
    import atgs.train.trainer as trainer_module

    calls, seen = [], []
    real_rasterize = api.rasterize

    def recording_rasterize(*args, **kwargs):
        out = real_rasterize(*args, **kwargs)
        seen.append((out.backend, args[0].device.type, args[0].requires_grad))
        return out

    monkeypatch.setattr(api, "rasterize", recording_rasterize)
    monkeypatch.setattr(trainer_module, "warm_up", lambda device, backend: calls.append((device, backend))
                        or api.warm_up(device, backend))
    scene = make_toy_scene(num_frames=6, num_cameras=4, width=32, height=24, keyframes=3)
    m, t = preset("tiny")
    t.render_backend, t.minutes = "torch", 0.5
    t.velocity_from_flow = False  # set-up the budget does pay for (test above)
    tr = Trainer(scene, m, t, tmp_path / "run")
    assert calls == [(torch.device("cpu"), "torch")]
    # (set-up renders with the CPU backend elsewhere too: carving random anchors, exposure)
    assert seen.count(("torch", "cpu", True)) == 1, "one Gaussian rendered with gradients on the trainer's backend"
    assert tr._session_start is None and tr._time_used() == 0.0, "before the budget's clock starts"


def test_the_cpu_kernels_build_in_set_up_not_in_the_budget(tmp_path, monkeypatch) -> None:
    """The grids' and the sparse optimizer's CPU kernels also compile on first use (seconds to a
    minute on 2 cores): the trainer asks for them while it sets up, before the clock starts."""
    import atgs.model.grids as grids
    import atgs.train.optim as optim
    import atgs.train.trainer as trainer_module

    asked = []
    real_grid_kernels, real_compiled = grids.grid_kernels, optim._compiled_kernel
    monkeypatch.setattr(trainer_module, "grid_kernels", lambda table, backend: asked.append(("grids", backend))
                        or real_grid_kernels(table, backend))
    monkeypatch.setattr(optim, "_compiled_kernel", lambda: asked.append(("optim", None)) or real_compiled())
    scene = make_toy_scene(num_frames=6, num_cameras=4, width=32, height=24, keyframes=3)
    m, t = preset("tiny")
    t.minutes, t.velocity_from_flow = 0.5, False  # the scene flow is set-up the budget pays for
    tr = Trainer(scene, m, t, tmp_path / "run")
    assert asked == [("optim", None), ("grids", "auto")]
    assert tr.sparse_opt._kernel is not None, "the compiled sparse Adam step serves the CPU tables"
    assert tr._session_start is None and tr._time_used() == 0.0, "before the budget's clock starts"


def test_iterations_and_minutes_together_are_refused(tmp_path, capsys) -> None:
    code = train_main(["--out", str(tmp_path / "r"), "tiny", "--train.iterations", "5", "--train.minutes", "1",
                       "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith("atgs-train: error: ") and "--train.minutes" in err and "\n" not in err
    assert not (tmp_path / "r").exists()


def test_presets_budget_and_fixed_steps() -> None:
    assert [preset(n)[1].minutes for n in ("cpu-fast", "cpu", "cpu-accurate", "paper", "tiny")] == [5, 20, 60, 0, 0]
    assert preset("cpu", iterations=300)[1].minutes == 0.0  # --iterations: exactly that many steps
    assert preset("paper", minutes=30)[1].minutes == 30.0


def test_evaluations_and_saves_stay_regular_when_the_budget_resizes_their_intervals(tmp_path) -> None:
    # A time budget rescales eval_every and save_every as its pace estimate moves; a check for
    # "step is a multiple of the interval" then skips evaluations (seen: none between steps 912
    # and 2550 of a 20-minute run evaluating every ~850 steps). Here the intervals change every step.
    import csv

    scene = make_toy_scene(num_frames=6, num_cameras=4, width=32, height=24, keyframes=3)
    m, t = preset("tiny")
    t = dataclasses.replace(t, iterations=60, eval_every=10, save_every=10, eval_max_frames=1)
    tr = Trainer(scene, m, t, tmp_path)
    saves = []
    real_save = tr.save
    tr.save = lambda *a, **k: (saves.append(tr.step), real_save(*a, **k))[1]

    def resize() -> bool:
        tr.cfg.eval_every = tr.cfg.save_every = 10 + tr.step % 3
        return False

    tr.run_steps(progress=False, should_stop=resize)
    rows = list(csv.DictReader(open(tmp_path / "train_log.csv")))
    evals = [int(r["step"]) for r in rows if r["eval_psnr"]]
    for steps in (evals, saves[:-1]):  # the last save is the end of the run
        gaps = [b - a for a, b in zip([0, *steps], steps)]
        assert len(steps) >= 4 and all(10 <= g <= 12 for g in gaps), steps


def test_an_evaluation_is_not_read_as_a_slow_step() -> None:
    """A 4-minute run at 0.5 s a step whose periodic evaluation at step 78 took 11 s once ended
    at step 79 (57 s in): the evaluation was read as the pace, and the final evaluation's
    reserve at that pace exceeded the time left. Reported as overhead, it is spread over the
    steps instead."""
    def run(report_overhead: bool) -> tuple[int, float, TimeBudget]:
        # re-planning after every step: the alignment the real run hit (a plan right after the
        # evaluation, over an interval of one step)
        b = TimeBudget(240.0, reserve_views=40, replan_seconds=0.5)
        step, used, overhead, planned = 0, 0.0, 0.0, 5000
        while step < planned:
            used += 0.5
            step += 1
            if step == 78:  # the evaluation
                used += 11.0
                overhead += 11.0
            n = b.plan(step, used, planned, overhead if report_overhead else 0.0)
            if n is not None:
                planned = n
        return step, used, b

    steps, used, b = run(report_overhead=False)
    assert steps > 100  # (it ended at 79 before; the reserve's mean pace alone now rides it out)
    steps, used, b = run(report_overhead=True)
    assert b.pace == pytest.approx(0.5)
    reserve = 40 * 0.5 + 1.0  # a step per view of the final evaluation
    assert b.reserve() == pytest.approx(reserve)
    # the time left after the evaluation and the reserve, at 0.5 s a step and the evaluation's
    # 11 s spread over the steps (an estimate that can only make the run end a little early)
    assert 240.0 - reserve - 30.0 <= used <= 240.0 - reserve + 1.0, (steps, used)


def test_trainer_reports_evaluations_and_saves_as_overhead(tmp_path) -> None:
    scene = make_toy_scene(num_frames=6, num_cameras=4, width=32, height=24, keyframes=3)
    m, t = preset("tiny")
    t = dataclasses.replace(t, minutes=0.5, iterations=40, eval_every=10, save_every=0, eval_max_frames=1)
    tr = Trainer(scene, m, t, tmp_path / "run")
    extra = [0.0]
    tr.clock = lambda: 0.5 * tr.step + extra[0]  # steps take 0.5 s, an evaluation 3 s more
    real_evaluate = tr.evaluate

    def slow_evaluate(*a, **k):
        extra[0] += 3.0
        return real_evaluate(*a, **k)

    tr.evaluate = slow_evaluate
    res = tr.run_steps(progress=False)
    assert extra[0] >= 3.0 and res["seconds_per_step"] == pytest.approx(0.5)
    assert res["seconds_used"] <= 30.0  # on time, evaluations included
    ck = torch.load(tmp_path / "run" / "ckpt.pt", weights_only=True)
    assert ck["trainer"]["budget"]["overhead"] == pytest.approx(extra[0])


def test_the_final_evaluations_reserve_is_measured_not_guessed(tmp_path) -> None:
    """As calibration begins, the trainer times the final evaluation on two frames and reserves that per
    view (with RESERVE_MARGIN), scaled with the pace: where a view costs a fifth of a step (held-out
    cameras sharing a frame's decode), a step per view would have kept most of the reserve idle."""
    from atgs.train.budget import RESERVE_MARGIN

    scene = make_toy_scene(num_frames=6, num_cameras=4, width=32, height=24, keyframes=3)
    tr = _budget_trainer(scene, tmp_path / "run", minutes=0.5)
    extra, probes = [0.0], []
    tr.clock = lambda: 0.5 * tr.step + extra[0]  # a step takes 0.5 s, an evaluated view 0.1 s
    real_evaluate = tr.evaluate

    def timed_evaluate(*a, frames=None, **k):
        probes.append((tr.step, tuple(frames), k.get("resolution_scale")))
        extra[0] += 0.1 * len(frames) * len(tr.test_idx)
        return real_evaluate(*a, frames=frames, **k)

    tr.evaluate = timed_evaluate
    res = tr.run_steps(progress=False)
    views = tr.final_views()
    # once, two frames timed apart, at full size
    assert len(probes) == 2 and all(len(p[1]) == 1 and p[2] == 1.0 and p[0] == probes[0][0] for p in probes), probes
    assert tr.budget.view_cost == pytest.approx(0.1 / 0.5)
    reserve = views * 0.1 * RESERVE_MARGIN + 1.0
    assert tr.budget.reserve() == pytest.approx(reserve)
    assert reserve < views * 0.5 + 1.0  # less than the step-per-view guess
    # the budget is filled up to the measured reserve, and the final evaluation fits in it
    assert 30.0 - reserve - 1.0 <= res["seconds_used"] <= 30.0 - reserve + 0.5, (res["seconds_used"], reserve)
    assert res["seconds_used"] + 0.1 * views <= 30.0
    ck = torch.load(tmp_path / "run" / "ckpt.pt", weights_only=True)
    assert ck["trainer"]["budget"]["view_cost"] == pytest.approx(0.2)  # a resume keeps the measurement
    assert ck["trainer"]["budget"]["overhead"] == pytest.approx(extra[0])  # the probe is not step time


def test_a_probe_that_reads_slow_reserves_no_more_than_a_step_per_view() -> None:
    """Two frames timed while another job ran read 2.35 steps a view on the built-in scene (1.07
    alone, 0.71 over a whole evaluation): the reserve keeps to the step per view of before, else
    the first plan shrinks (to 31 steps of a 5-minute run there) and freezes at 90 %."""
    b = TimeBudget(300.0, reserve_views=120, skip_steps=1, calibration_steps=4)
    b.plan(1, 1.0, 1000)  # calibration begins
    assert b.wants_view_cost
    b.measured_view(3.0)  # 3 s a view at 1 s a step
    step, used, plans = simulate(b, lambda s: 1.0, 1000, step=1, used=1.0)
    assert b.view_cost == pytest.approx(3.0)
    assert b.reserve() == pytest.approx(120 * 1.0 + 1.0)  # capped: a step per view
    assert used >= 0.8 * (300.0 - b.reserve()), (step, used, plans)
    wide = TimeBudget(300.0, reserve_views=120, max_view_cost=4.0)  # trained at half resolution
    wide.view_cost, wide._pace = 4.0, 1.0  # x RESERVE_MARGIN: over the cap
    assert wide.reserve() == pytest.approx(120 * 4.0 + 1.0)



def test_a_slow_half_minute_late_in_the_run_does_not_freeze_a_short_plan() -> None:
    """The 20-minute ring run of 2026-11-29: 0.24 s a step, then 40 steps at 1.3 s (a test run
    beside it) at step 3,139. Its plan, sized by that one interval, fell from 4,794 to 3,458 steps,
    already past the 90 % freeze, and the run ended with 285 s unused. The median of the last
    intervals' paces rides the patch out."""
    def pace(step: int) -> float:
        return 1.3 if 3139 <= step < 3179 else 0.24

    b = TimeBudget(1200.0, reserve_views=120)
    steps, used, plans = simulate(b, pace, 5000)
    assert used >= 0.97 * (1200.0 - b.reserve()), (steps, used, plans)
    assert used <= 1200.0 - b.reserve() + 2 * 1.3
