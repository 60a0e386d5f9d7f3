"""What the training benches share: a Trainer built from a scene, a preset and a case's
overrides, and its run or its steps timed.

Every bench script builds its Trainer through :func:`build_trainer`, so what a bench relies on
is set in one place: periodic evaluations and checkpoints off (a bench times the steps and
scores once, at the end), the case's torch threads, torch's global seed (the trainer's own
``seed``), and a run folder emptied first (a checkpoint or an evaluation image of an earlier run
never mixes in). Only the trainer's public surface is used: its constructor, ``train_step()``,
``run_steps()``, ``train()`` and ``final_evaluation()``.
"""

from __future__ import annotations

import dataclasses
import shutil
import time
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Any, NamedTuple

import torch

from atgs.train.config import ModelConfig, TrainConfig, preset
from atgs.train.trainer import StepResult, Trainer

NONE: Mapping[str, Any] = MappingProxyType({})  # no overrides

# How a timed run ends (run_timed): without an evaluation (the bench scores the model itself),
# with the trainer's held-out scores after the timed span, or as atgs-train ends (the final
# evaluation writing its images to OUT/eval), inside the timed span.
FINALS = ("none", "scores", "renders")


def set_fields(cfg: Any, overrides: Mapping[str, Any]) -> None:
    """Set ``overrides`` on the config dataclass ``cfg`` in place. A nested config is reached by
    a dotted key ("densify.grad_threshold") or a nested mapping ({"hash": {"levels": 8}}); an
    unknown field is an error, so that a case's typo cannot pass as the preset's value."""
    for key, value in overrides.items():
        obj, *path = cfg, *key.split(".")
        for name in path[:-1]:
            obj = _field(obj, name, key)
        if isinstance(value, Mapping):
            set_fields(_field(obj, path[-1], key), value)
        else:
            _field(obj, path[-1], key)
            setattr(obj, path[-1], value)


def _field(obj: Any, name: str, key: str) -> Any:
    if not dataclasses.is_dataclass(obj) or name not in {f.name for f in dataclasses.fields(obj)}:
        raise ValueError(f"override {key!r}: {type(obj).__name__} has no field {name!r}")
    return getattr(obj, name)


def case_configs(preset_name: str, *, iterations: int | None = None, minutes: float | None = None,
                 model: Mapping[str, Any] = NONE, train: Mapping[str, Any] = NONE,
                 threads: int = 1) -> tuple[ModelConfig, TrainConfig]:
    """(model, train) configs of a bench case: the preset (``iterations``: a fixed step count,
    ``minutes``: a time budget; neither: the preset's own), the case's overrides, no periodic
    evaluation or checkpoint, and ``threads`` torch threads (0: torch's default)."""
    m, t = preset(preset_name, iterations, minutes)
    set_fields(m, model)
    set_fields(t, train)
    t.eval_every = t.save_every = 0
    t.threads = threads
    return m, t


def build_trainer(scene, out: Path, preset_name: str, *, iterations: int | None = None,
                  minutes: float | None = None, model: Mapping[str, Any] = NONE, train: Mapping[str, Any] = NONE,
                  threads: int = 1, device: str = "cpu", progress: bool = False) -> Trainer:
    """A fresh Trainer of :func:`case_configs` on ``scene`` writing to ``out`` (emptied first),
    torch's global seed set to the trainer's seed. ``progress``: the set-up's progress bar."""
    m, t = case_configs(preset_name, iterations=iterations, minutes=minutes, model=model, train=train,
                        threads=threads)
    shutil.rmtree(out, ignore_errors=True)
    torch.manual_seed(t.seed)
    return Trainer(scene, m, t, out, device=device, progress=progress)


class Timed(NamedTuple):
    result: dict  # what the trainer's run returned; with an evaluation, its scores under "eval"
    seconds: float

    @property
    def eval(self) -> dict:
        return self.result["eval"]


def run_timed(tr: Trainer, final: str = "scores", progress: bool = False) -> Timed:
    """Train to the end of the schedule (or of the time budget), timed; ``final``: see FINALS."""
    if final not in FINALS:
        raise ValueError(f"final={final!r}: use one of {', '.join(FINALS)}")
    t0 = time.perf_counter()
    if final == "renders":
        result = tr.train(progress=progress, final_renders=True)
    else:
        result = tr.run_steps(progress=progress)
    seconds = time.perf_counter() - t0
    if final == "scores":
        result["eval"] = tr.final_evaluation(None)
    return Timed(result, seconds)


def timed_steps(tr: Trainer, steps: int) -> tuple[list[StepResult], float]:
    """``steps`` training steps and their wall seconds; on a GPU the queued kernels are waited
    for before and after, so the seconds are those of the steps."""
    sync = torch.cuda.synchronize if tr.device.type == "cuda" else (lambda: None)
    sync()
    t0 = time.perf_counter()
    results = [tr.train_step() for _ in range(steps)]
    sync()
    return results, time.perf_counter() - t0
