"""The ranges a configuration field accepts, and the one-line error for a value outside them.

The config dataclasses (``atgs.model.config``, ``atgs.train.config``, ``atgs.cli.train_args.TrainArgs``)
check themselves in ``__post_init__`` with :func:`check_fields`, so a bad flag is refused while the
command line is read, before anything touches ``--out``; the trainer asks them again because fields
can be set after construction. :class:`ConfigError` is a :class:`~atgs.errors.UserError` and not a
``ValueError``: tyro would box a ``ValueError`` raised while it builds a config, where ``run_cli``
prints one line ``<command>: error: <message>`` with exit code 2.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
import typing

from atgs.errors import UserError


class ConfigError(UserError):
    """A configuration value outside its range; the message names the flag and what it accepts."""


@dataclass(frozen=True)
class Range:
    accepts: Callable[[typing.Any], bool]  # false for NaN, as every comparison with it is
    need: str  # what to pass instead, e.g. "use >= 1"


def _need(rule: str, what: str, note: str) -> str:
    """"a loss weight, use >= 0 (0 = off)": what the field is, the rule, a note on special values."""
    return (f"{what}, " if what else "") + rule + (f" ({note})" if note else "")


def at_least(low: float, what: str = "", note: str = "") -> Range:
    return Range(lambda v: v >= low, _need(f"use >= {low:g}", what, note))


def above(low: float, what: str = "", note: str = "") -> Range:
    return Range(lambda v: v > low, _need(f"use > {low:g}", what, note))


def between(low: float, high: float, what: str = "", note: str = "", high_open: bool = False) -> Range:
    if high_open:
        return Range(lambda v: low <= v < high, _need(f"use {low:g} <= value < {high:g}", what, note))
    return Range(lambda v: low <= v <= high, _need(f"use {low:g} <= value <= {high:g}", what, note))


def one_of(choices: typing.Any) -> Range:
    """``choices``: a ``Literal`` type or a tuple of the accepted values."""
    values = typing.get_args(choices) or tuple(choices)
    return Range(lambda v: v in values, f"use one of {', '.join(map(str, values))}")


def each(inner: Range) -> Range:
    """Every element of a tuple field in ``inner``'s range."""
    return Range(lambda vs: all(inner.accepts(v) for v in vs), f"each value: {inner.need}")


def flag_of(prefix: str, field: str) -> str:
    """The command-line flag of a config field: ``flag_of("--train.lr.", "warmup_steps")``."""
    return prefix + field.replace("_", "-")


def check_fields(cfg: object, prefix: str, ranges: dict[str, Range]) -> None:
    """Raise :class:`ConfigError` for the first field of ``cfg`` outside its range; ``prefix``:
    where the command line nests the config (``"--train."``), so the message names the flag."""
    for field, rng in ranges.items():
        value = getattr(cfg, field)
        if value is not None and not rng.accepts(value):  # (None: an optional flag not given)
            shown = repr(value) if isinstance(value, str) else value
            raise ConfigError(f"{flag_of(prefix, field)} {shown}: {rng.need}")
