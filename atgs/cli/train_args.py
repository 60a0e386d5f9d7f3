"""The command line of ``atgs-train``: its flags, its presets and the old spellings.

    atgs-train [cpu-fast|cpu|cpu-accurate|paper|tiny] --data DIR --out DIR
               [--train.minutes M | --train.iterations N] [--resume] [--device auto|cpu|cuda] [--workers N]

A preset is a tyro subcommand (default ``cpu``): it gives every ``--model.*`` and ``--train.*``
flag its default, and the flags given after it override them (``atgs-train cpu-fast --help``
lists them with the preset's values). The flags of the run (--data, --out, --resume, ...) go
before or after it. Each flag has one spelling; the old ones (OLD_SPELLINGS, ``--preset NAME``)
work for one more release, each with a one-line note.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
import os
from pathlib import Path
import sys
from typing import Annotated, Union

import tyro

from atgs.config_checks import ConfigError, above, at_least, check_fields
from atgs.device import DeviceName
from atgs.io.cache import cache_dir
from atgs.model.config import ModelConfig
from atgs.train.config import DEFAULT_PRESET, PRESET_HELP, PRESET_NAMES, PresetName, TrainConfig, preset
from atgs.train.step_schedule import SCHEDULE_SETTINGS, schedule_for

PROG = "atgs-train"
OLD_SPELLINGS = {"--iterations": "--train.iterations", "--minutes": "--train.minutes"}  # (go in the next release)


@dataclass
class Preset:
    """A preset's model and trainer configuration; every field is a flag (--model.*, --train.*)."""

    name: tyro.conf.Suppress[PresetName] = DEFAULT_PRESET
    model: Annotated[ModelConfig, tyro.conf.arg(prefix_name=False)] = field(default_factory=ModelConfig)
    train: Annotated[TrainConfig, tyro.conf.arg(prefix_name=False)] = field(default_factory=TrainConfig)

    @classmethod
    def named(cls, name: str) -> Preset:
        model, train = preset(name)
        return cls(name, model, train)


# One subcommand per preset, its defaults the preset's (tyro applies the flags given over them).
PresetChoice = Union[tuple(
    Annotated[Preset, tyro.conf.subcommand(name, default=Preset.named(name), description=PRESET_HELP[name],
                                           prefix_name=False, is_default=name == DEFAULT_PRESET)]
    for name in PRESET_NAMES)]


def _of_preset(name: str, kind: type) -> property:
    """``args.model`` / ``args.train``: the configuration in ``args.preset`` (read and replaced)."""
    return property(lambda self: getattr(self.preset, name), lambda self, value: setattr(self.preset, name, value),
                    doc=f"The run's {kind.__name__} (the preset's, with the flags given).")


@dataclass
class TrainArgs:
    """Train ATGS on a prepared scene (or the built-in synthetic scene). Nothing in an existing --out
    changes before the new run's first checkpoint; Ctrl-C saves a checkpoint that --resume continues."""

    out: Path = Path("runs/atgs")
    """Output directory: ckpt.pt, train_log.csv, config.json, result.json, eval/."""
    data: Path | None = None
    """Prepared scene directory (atgs-prepare); default: the built-in synthetic scene."""
    resume: bool = False
    """Continue the run in --out from its ckpt.pt (configuration from the checkpoint; --train.iterations
    or --train.minutes: the new total, time already used counting)."""
    overwrite: bool = False
    """Start a new run even if --out already holds a checkpoint (it is replaced at the first save)."""
    device: DeviceName = "auto"
    """Where to train: cuda (the GPU; gsplat rasterizes), cpu (the compiled CPU rasterizer),
    auto (cuda when torch sees a GPU and gsplat imports, else cpu). --resume may change it."""
    progress: bool = True
    cache_dir: Path = field(default_factory=cache_dir)
    """Where the built-in synthetic scene is cached (default: $ATGS_CACHE_DIR, else ~/.cache/atgs)."""
    synth_keyframes: int = 6
    """Keyframes of the built-in synthetic scene (when --data is not given)."""
    auto: bool = False
    """Measure the scene's motion and choose K, M, hash table size and spatial grid resolution
    from it (printed with the reasons); --model.* flags given explicitly still win."""
    workers: int = 1
    """Worker processes on this machine, each rendering its share of every step's views, their
    gradients summed (torch.distributed: gloo on the CPU, NCCL on CUDA; docs/training.md, "Several
    workers"). N > 1 runs torchrun's launcher here (as torchrun --nproc-per-node N -m
    atgs.cli.train would); without --train.views-per-step, a new run takes at least N views per
    step (one each; a value given must be at least N)."""
    max_restarts: int = 0
    """With --workers N: after a worker fails (killed, crashed, lost), torchrun restarts all of
    them this many times; the restarted workers continue from the last checkpoint of this start's
    run, as --resume does (steps after it are trained again), or start afresh when there is none
    (a replaced run's is not continued). 0: a failure stops the run with one line."""
    worker_timeout: float = 1800.0
    """Seconds a worker waits for the others in an exchange before it stops (several workers;
    rank 0's set-up of the velocities from optical flow must fit in it; a worker that dies is noticed at once)."""
    preset: PresetChoice = field(default_factory=lambda: Preset.named(DEFAULT_PRESET))
    """The preset (a subcommand): the defaults of every --model.* and --train.* flag."""
    iterations: tyro.conf.Suppress[int | None] = None
    """(Set by parse) the step count given (--train.iterations without a budget): a resume's new total."""
    minutes: tyro.conf.Suppress[float | None] = None
    """(Set by parse) the time budget given (--train.minutes): a resume's new total."""

    model = _of_preset("model", ModelConfig)
    train = _of_preset("train", TrainConfig)

    def __post_init__(self) -> None:
        check_fields(self, "--", {"workers": at_least(1, "a number of processes"),
                                  "max_restarts": at_least(0, "a number of restarts"),
                                  "worker_timeout": above(0, "seconds")})


def current_spelling(argv: list[str]) -> list[str]:
    """``argv`` with each old spelling replaced by its flag (one note each on stderr, rank 0 only):
    OLD_SPELLINGS, and ``--preset NAME``, whose subcommand goes first (before the flags it sets)."""
    out: list[str] = []
    chosen: list[str] = []
    rest = iter(argv)
    for arg in rest:
        flag, eq, value = arg.partition("=")
        if flag in OLD_SPELLINGS:
            out.append(OLD_SPELLINGS[flag] + eq + value)
            _note(f"{flag} is now {OLD_SPELLINGS[flag]}")
        elif flag == "--preset":
            name = value if eq else next(rest, "")
            if name not in PRESET_NAMES:
                raise ConfigError(f"--preset {name!r}: use one of {', '.join(PRESET_NAMES)}")
            chosen.append(name)
            _note(f"--preset {name} is now a subcommand ({PROG} {name} --data ...)")
        else:
            out.append(arg)
    return chosen + out


def _note(change: str) -> None:
    if int(os.environ.get("RANK", "0")) == 0:  # (torchrun's other workers parse the same flags)
        print(f"{PROG}: note: {change}; the old spelling goes in the next release", file=sys.stderr, flush=True)


def given_flags(argv: list[str], prefix: str) -> set[str]:
    """Flags under ``prefix`` given on the command line, as they follow it with '-' for '_'
    (``--train.lr.warmup_steps=9`` -> "lr.warmup-steps")."""
    return {a[len(prefix):].split("=", 1)[0].replace("_", "-") for a in argv if a.startswith(prefix)}


def explicit_model_flags(argv: list[str]) -> set[str]:
    """Model knobs given on the command line, as dotted field names ("hash.log2_table_size")."""
    return {name.replace("-", "_") for name in given_flags(argv, "--model.")}


def parse(argv: list[str]) -> TrainArgs:
    """The arguments: the preset's values with the flags given over them, and the step count's
    schedule: --train.iterations (without a --train.minutes budget) sizes the schedule by the one
    rule (atgs.train.step_schedule), except the schedule flags given, which are kept at any step
    count (also when a budget re-sizes it)."""
    argv = current_spelling(argv)
    args = tyro.cli(TrainArgs, args=argv, prog=PROG, config=(tyro.conf.CascadeSubcommandArgs,))
    given = given_flags(argv, "--train.")
    pinned = tuple(s for s in SCHEDULE_SETTINGS if s in given and s not in args.train.fixed_schedule)
    args.train = replace(args.train, fixed_schedule=args.train.fixed_schedule + pinned)
    if "minutes" in given:
        args.minutes = args.train.minutes
    if "iterations" in given:
        if args.minutes:
            raise ConfigError(f"--train.iterations and --train.minutes {args.minutes:g} were both given; pass one "
                              "(--train.iterations N runs exactly N steps, --train.minutes M sizes the steps to "
                              "M minutes)")
        args.iterations = args.train.iterations
        args.train = schedule_for(replace(args.train, minutes=0.0), args.iterations)
    return args
