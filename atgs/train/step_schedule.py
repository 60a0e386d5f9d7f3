"""The one rule that sizes a training schedule to a step count.

Five settings of a :class:`~atgs.train.config.TrainConfig` count steps: the densification start
and interval, the learning-rate warm-up, and the evaluation and checkpoint intervals.
:func:`schedule_for` sizes them for a run of N steps, and everything that chooses N goes through
it: the presets (at their own step counts), ``atgs-train --train.iterations N``,
``--resume --train.iterations N``, and a ``--train.minutes`` budget each time it
re-plans (atgs.train.budget). So a run of N steps has one schedule however N was chosen.

The rule is the CPU presets' (tuned with them, docs/training.md): each setting is
``max(floor, N // per)``, e.g. densify every ``max(50, N // 60)`` steps. A setting named in
``TrainConfig.fixed_schedule`` keeps its value at any N: the ``paper`` preset fixes all five (the
paper's schedule), and atgs-train adds those given as flags, so ``--train.eval-every 100`` means
every 100 steps with a budget too. An interval or warm-up of 0 (off) stays off.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Literal, get_args

if TYPE_CHECKING:
    from atgs.train.config import TrainConfig

# spelled as the flags after "--train." (the config's attribute path, '-' for '_')
ScheduleSetting = Literal["densify.start", "densify.interval", "lr.warmup-steps", "eval-every", "save-every"]
SCHEDULE_SETTINGS: tuple[str, ...] = get_args(ScheduleSetting)


@dataclass(frozen=True)
class StepRule:
    """A setting of ``max(floor, steps // per)`` steps."""

    floor: int
    per: int
    zero_is_off: bool  # 0 means "never" (no evaluations, no warm-up), not a step count

    def size(self, steps: int, current: int) -> int:
        if self.zero_is_off and current <= 0:
            return current
        return max(self.floor, steps // self.per)


RULES: dict[str, StepRule] = {
    "densify.start": StepRule(100, 20, zero_is_off=False),
    "densify.interval": StepRule(50, 60, zero_is_off=False),
    "lr.warmup-steps": StepRule(1, 30, zero_is_off=True),
    "eval-every": StepRule(500, 4, zero_is_off=True),
    "save-every": StepRule(500, 6, zero_is_off=True),
}


def _attrs(setting: str) -> list[str]:
    return [part.replace("-", "_") for part in setting.split(".")]


def setting_of(cfg: "TrainConfig", setting: str) -> int:
    value = cfg
    for attr in _attrs(setting):
        value = getattr(value, attr)
    return value


def _with(cfg, attrs: list[str], value: int):
    """``cfg`` with the nested field ``attrs`` set to ``value`` (new dataclasses, validated)."""
    head, rest = attrs[0], attrs[1:]
    return replace(cfg, **{head: _with(getattr(cfg, head), rest, value) if rest else value})


def schedule_for(cfg: "TrainConfig", steps: int) -> "TrainConfig":
    """``cfg`` for a run of ``steps`` steps: ``iterations`` and every setting not in
    ``cfg.fixed_schedule`` sized by the rule (the module's notes). Nothing else changes."""
    sized = replace(cfg, iterations=int(steps))
    for setting, rule in RULES.items():
        if setting not in cfg.fixed_schedule:
            sized = _with(sized, _attrs(setting), rule.size(int(steps), setting_of(cfg, setting)))
    return sized


def schedule_of(cfg: "TrainConfig") -> dict[str, int]:
    """The step count and the five settings, by flag name (what a run of ``cfg`` follows)."""
    return {"iterations": cfg.iterations, **{s: setting_of(cfg, s) for s in SCHEDULE_SETTINGS}}
