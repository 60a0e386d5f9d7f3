"""A training time budget (``atgs-train --train.minutes``).

A fixed step count wastes a user's time either way: the same preset finished the built-in scene
in 16 minutes and a smaller capture in 3. With a budget, the number of steps is sized from the
measured step time, and re-sized while training, since densification grows the model and with
it the step time. The trainer sizes the whole schedule (warm-up, densification window and interval,
learning-rate decay, periodic evaluation and checkpoints, final pruning) to the steps the budget
affords by the rule every step count follows (atgs.train.step_schedule: a budget that lands on N
steps trains as ``--train.iterations N`` would), so a run always ends with a complete schedule, on time. (If the pace drops sharply late
in the run, the run ends when the time is up, with its final pruning.)

What is measured: wall time of the training steps, periodic evaluations and checkpoints of this
run, across resumes (the checkpoint carries the time used). The pace of a step is measured
without the evaluations and checkpoints (the trainer reports their seconds as overhead), whose
cost is spread over the steps as an average: one evaluation must not read as one very slow
step (it once ended a 4-minute run after 79 steps, 57 s in). The final evaluation is reserved
inside the budget. Until it is measured, at one step per view at the run's mean pace (with
atgs-eval, a view cost 0.71 of a step on the built-in scene and 0.85 on a 5-camera 160x120 one;
half a step, an earlier guess, made runs end late). Once calibrated, the trainer times the final
evaluation itself on two frames, each timed alone, the faster one (:meth:`TimeBudget.measured_view`), and the reserve is that
cost per view, in steps, at the mean pace, so it grows with the model as the steps do, plus
RESERVE_MARGIN, never more than the step per view reserved before (``max_view_cost``): two
frames timed on a busy machine can read several times their cost (2.35 steps a view on the
built-in scene with the test suite running beside it, 1.07 alone, where atgs-eval measured
0.71 over all frames), and an inflated reserve would shrink the first plan and, once 90 % of
it is done, freeze it. A view is far cheaper than a step where several held-out cameras share a
frame's decode: on a 27-camera stage with 4 held-out cameras x 120 frames, one step per view
reserved 552 s of a 20-minute run for an evaluation that took 181 s. Scene loading and model
set-up come on top (the
trainer compiles its rasterizer while it sets up: ``atgs.render.warm_up``).
Runs with a budget are not bit-reproducible (their length depends on the machine); a fixed
``--train.iterations`` run is.
"""

from __future__ import annotations

from dataclasses import dataclass, field

# Re-sizing stops once this fraction of the planned steps is done: the learning rates are then
# far into their decay and moving the end would bend it visibly. The last steps run as planned
# unless time runs out, which ends the run at once (with its final pruning).
FREEZE_FRACTION = 0.9
MIN_STEPS = 10
# The pace a plan uses: the median of the last few intervals' paces. A slow patch (another job on
# the machine for half a minute) no longer sizes the plan alone: read from its one interval, it
# once shrank a 20-minute ring run's plan from 4,794 to 3,458 steps at step 3,164, past the freeze
# at 90 %, and the run ended with 285 s unused. A lasting change of pace is taken within two plans.
PACE_INTERVALS = 3
# The measured reserve's headroom: the probe times two frames (the faster one), the final evaluation all of them.
RESERVE_MARGIN = 1.25


@dataclass
class TimeBudget:
    """Plans the step count of a run that has ``seconds`` of training time.

    Call :meth:`plan` after every step with the step count and the seconds used so far; it
    returns a new total step count when the plan changes. The first plan comes after
    ``calibration_steps`` steps (the first few, which warm caches up, are not timed); later
    plans use the pace since the previous one."""

    seconds: float
    used: float = 0.0  # seconds spent before this session (restored on resume)
    overhead: float = 0.0  # of which periodic evaluations and checkpoints (restored on resume)
    calibration_steps: int = 25
    skip_steps: int = 5
    replan_seconds: float = 0.0  # 0: seconds / 40, at least 10 s
    reserve_views: int = 16  # views rendered by the final evaluation, reserved in the budget
    # a view of the final evaluation in steps at the mean pace (measured_view); None until measured
    view_cost: float | None = None
    # the most a view may be reserved, in steps: the rule before the measurement (a step per view,
    # 1 / resolution_scale^2 when training at a lower resolution than the full-size evaluation)
    max_view_cost: float = 1.0
    # (step, seconds, overhead seconds) when calibration began / of the last plan
    _start: tuple[int, float, float] | None = field(default=None, repr=False)
    _mark: tuple[int, float, float] | None = field(default=None, repr=False)
    _pace: float = field(default=0.0, repr=False)  # measured seconds per step, overhead excluded
    _recent: list[float] = field(default_factory=list, repr=False)  # the last intervals' paces
    _overhead_per_step: float = field(default=0.0, repr=False)  # evaluations and saves, averaged
    # seconds per step since calibration began: the final evaluation's reserve is sized by it, so
    # that a short slow patch (another job on the machine) does not swell a reserve of hundreds of
    # views and freeze a plan that ends the run at once (a 20-minute run once ended after 229 s)
    _mean_pace: float = field(default=0.0, repr=False)
    _view_seconds: float | None = field(default=None, repr=False)  # measured_view's, until the first plan

    def __post_init__(self) -> None:
        if not self.seconds > 0:
            raise ValueError(f"a time budget must be positive, got {self.seconds} s")
        if self.replan_seconds <= 0:
            self.replan_seconds = max(10.0, self.seconds / 40)

    @property
    def pace(self) -> float:
        """Measured seconds per training step (0 before the first plan)."""
        return self._pace

    def reserve(self) -> float:
        """Seconds kept for the final evaluation at the run's mean pace: its measured cost per view
        with RESERVE_MARGIN, or a step per view before it is measured (see the module's notes)."""
        per_view = self.max_view_cost if self.view_cost is None else min(self.view_cost * RESERVE_MARGIN,
                                                                          self.max_view_cost)
        return self.reserve_views * per_view * (self._mean_pace or self._pace) + 1.0

    @property
    def wants_view_cost(self) -> bool:
        """Calibration has begun and the final evaluation's cost is not measured yet."""
        return self._start is not None and self.view_cost is None and self._view_seconds is None

    def measured_view(self, seconds: float) -> None:
        """The final evaluation takes ``seconds`` a view (the trainer's probe: the faster of two frames, as
        calibration begins): the first plan turns it into steps at the pace it measures, and the
        reserve follows it from then on, scaled with the mean pace."""
        self._view_seconds = max(0.0, float(seconds))

    def plan(self, step: int, used: float, planned: int, overhead: float = 0.0) -> int | None:
        """New total step count, or None to keep ``planned``. ``step``: steps done; ``used``:
        seconds used so far, earlier sessions included; ``overhead``: the part of ``used`` that
        went to periodic evaluations and checkpoints."""
        if step >= planned:
            return None
        if self.seconds - used - self.reserve() <= 0:
            return step  # out of time: end now (the trainer runs the final pruning)
        if self._mark is None:  # calibrating: time steps skip_steps .. skip_steps + calibration_steps
            if step < self.skip_steps:
                return None
            if self._start is None:
                self._start = (step, used, overhead)
                return None
            if step - self._start[0] < self.calibration_steps:
                return None
            return self._replan(step, used, overhead, self._start, planned)
        if step >= FREEZE_FRACTION * planned or used - self._mark[1] < self.replan_seconds:
            return None
        return self._replan(step, used, overhead, self._mark, planned)

    def _replan(self, step: int, used: float, overhead: float, since: tuple[int, float, float],
                planned: int) -> int | None:
        s0, u0, o0 = since
        self._recent = (self._recent + [max(0.0, (used - overhead) - (u0 - o0)) / max(1, step - s0)])[-PACE_INTERVALS:]
        self._pace = sorted(self._recent)[len(self._recent) // 2]  # (of two, the slower)
        if self._start is not None:
            s1, u1, o1 = self._start
            self._mean_pace = max(0.0, (used - overhead) - (u1 - o1)) / max(1, step - s1)
        self._overhead_per_step = overhead / max(1, step)
        if self.view_cost is None and self._view_seconds is not None and self._pace > 0:
            self.view_cost = self._view_seconds / (self._mean_pace or self._pace)
        self._mark = (step, used, overhead)
        left = self.seconds - used - self.reserve()
        per_step = max(self._pace + self._overhead_per_step, 1e-9)
        n = max(MIN_STEPS, step + 1, step + int(max(0.0, left) / per_step))
        return None if n == planned else n

    # --- checkpoints ---------------------------------------------------------------------------
    def state_dict(self, used: float, overhead: float = 0.0) -> dict:
        return {"seconds": float(self.seconds), "used": float(used), "overhead": float(overhead),
                "pace": float(self._pace), "overhead_per_step": float(self._overhead_per_step),
                "mean_pace": float(self._mean_pace), "view_cost": self.view_cost}

    @classmethod
    def resumed(cls, state: dict, seconds: float) -> "TimeBudget":
        """The budget of a resumed run: ``seconds`` in all (the time used before counts). (Older
        checkpoints also hold the schedule the budget used to scale from: not needed any more.)"""
        b = cls(seconds=seconds, used=float(state["used"]), overhead=float(state.get("overhead", 0.0)))
        b._pace = float(state.get("pace", 0.0))
        b._overhead_per_step = float(state.get("overhead_per_step", 0.0))
        b._mean_pace = float(state.get("mean_pace", 0.0))
        b.view_cost = state.get("view_cost")  # (None: older checkpoints, or not measured yet)
        return b

    def steps_left(self) -> int | None:
        """Steps the remaining time affords at the last measured pace (None before any)."""
        if self._pace <= 0:
            return None
        per_step = self._pace + self._overhead_per_step
        return max(0, int((self.seconds - self.used - self.reserve()) / per_step))
