"""A training time budget (``atgs-train --minutes``).

A fixed step count wastes a user's time either way: the same preset finished the built-in scene
in 16 minutes and a smaller capture in 3. With a budget, the number of steps is sized from the
measured step time, and re-sized while training, since densification grows the model and with
it the step time. The whole schedule (warm-up, densification window and interval, learning-rate
decay, periodic evaluation and checkpoints, final pruning) is stretched over the steps the budget
affords, so a run always ends with a complete schedule, on time. (If the pace drops sharply late
in the run, the run ends when the time is up, with its final pruning.)

What is measured: wall time of the training steps, periodic evaluations and checkpoints of this
run, across resumes (the checkpoint carries the time used). The final evaluation is reserved
inside the budget from the measured step time. Scene loading and model set-up come on top (the
trainer compiles its rasterizer while it sets up: ``atgs.render.warm_up``).
Runs with a budget are not bit-reproducible (their length depends on the machine); a fixed
``--iterations`` run is.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

# Re-sizing stops once this fraction of the planned steps is done: the learning rates are then
# far into their decay and moving the end would bend it visibly. The last steps run as planned
# unless time runs out, which ends the run at once (with its final pruning).
FREEZE_FRACTION = 0.9
MIN_STEPS = 10


@dataclass(frozen=True)
class ScheduleBase:
    """The iteration-dependent part of a TrainConfig at the preset's own step count; every
    re-sizing scales it from here (not from the last re-sizing, so rounding never drifts)."""

    iterations: int
    densify_start: int
    densify_interval: int
    warmup_steps: int
    eval_every: int
    save_every: int

    @classmethod
    def of(cls, cfg) -> "ScheduleBase":
        return cls(cfg.iterations, cfg.densify.start, cfg.densify.interval, cfg.lr.warmup_steps,
                   cfg.eval_every, cfg.save_every)


def rescale_schedule(cfg, base: ScheduleBase, iterations: int) -> None:
    """Set ``cfg`` (a TrainConfig) to ``iterations`` steps with every interval scaled alike."""
    f = iterations / base.iterations

    def scaled(v: int) -> int:
        return 0 if v <= 0 else max(1, round(v * f))

    cfg.iterations = int(iterations)
    cfg.densify.start = scaled(base.densify_start)
    cfg.densify.interval = scaled(base.densify_interval)
    cfg.lr.warmup_steps = scaled(base.warmup_steps)
    cfg.eval_every = scaled(base.eval_every)
    cfg.save_every = scaled(base.save_every)


@dataclass
class TimeBudget:
    """Plans the step count of a run that has ``seconds`` of training time.

    Call :meth:`plan` after every step with the step count and the seconds used so far; it
    returns a new total step count when the plan changes. The first plan comes after
    ``calibration_steps`` steps (the first few, which warm caches up, are not timed); later
    plans use the pace since the previous one."""

    seconds: float
    base: ScheduleBase
    used: float = 0.0  # seconds spent before this session (restored on resume)
    calibration_steps: int = 25
    skip_steps: int = 5
    replan_seconds: float = 0.0  # 0: seconds / 40, at least 10 s
    reserve_views: int = 16  # views rendered by the final evaluation, reserved in the budget
    _start: tuple[int, float] | None = field(default=None, repr=False)  # (step, seconds) calibration began
    _mark: tuple[int, float] | None = field(default=None, repr=False)  # (step, seconds) of the last plan
    _pace: float = field(default=0.0, repr=False)  # measured seconds per step

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
        """Seconds kept for the final evaluation (a view renders in about half a step)."""
        return 0.5 * self.reserve_views * self._pace + 1.0

    def plan(self, step: int, used: float, planned: int) -> int | None:
        """New total step count, or None to keep ``planned``. ``step``: steps done; ``used``:
        seconds used so far, earlier sessions included."""
        if step >= planned:
            return None
        if self.seconds - used - self.reserve() <= 0:
            return step  # out of time: end now (the trainer runs the final pruning)
        if self._mark is None:  # calibrating: time steps skip_steps .. skip_steps + calibration_steps
            if step < self.skip_steps:
                return None
            if self._start is None:
                self._start = (step, used)
                return None
            if step - self._start[0] < self.calibration_steps:
                return None
            return self._replan(step, used, *self._start, planned)
        s0, u0 = self._mark
        if step >= FREEZE_FRACTION * planned or used - u0 < self.replan_seconds:
            return None
        return self._replan(step, used, s0, u0, planned)

    def _replan(self, step: int, used: float, s0: int, u0: float, planned: int) -> int | None:
        self._pace = (used - u0) / max(1, step - s0)
        self._mark = (step, used)
        left = self.seconds - used - self.reserve()
        n = max(MIN_STEPS, step + 1, step + int(max(0.0, left) / max(self._pace, 1e-9)))
        return None if n == planned else n

    # --- checkpoints ---------------------------------------------------------------------------
    def state_dict(self, used: float) -> dict:
        return {"seconds": float(self.seconds), "used": float(used), "base": asdict(self.base),
                "pace": float(self._pace)}

    @classmethod
    def resumed(cls, state: dict, seconds: float) -> "TimeBudget":
        """The budget of a resumed run: ``seconds`` in all (the time used before counts)."""
        b = cls(seconds=seconds, base=ScheduleBase(**state["base"]), used=float(state["used"]))
        b._pace = float(state.get("pace", 0.0))
        return b

    def steps_left(self) -> int | None:
        """Steps the remaining time affords at the last measured pace (None before any)."""
        if self._pace <= 0:
            return None
        return max(0, int((self.seconds - self.used - self.reserve()) / self._pace))
