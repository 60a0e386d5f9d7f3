"""What the training benches share: a synthetic scene, a Trainer built from a scene, a preset
and a case's overrides, its run or its steps timed, and the child processes that run cases.

Every bench script builds its Trainer through :func:`build_trainer`, so what a bench relies on
is set in one place: periodic evaluations and checkpoints off (a bench times the steps and
scores once, at the end), the case's torch threads, torch's global seed (the trainer's own
``seed``), and a run folder emptied first (a checkpoint or an evaluation image of an earlier run
never mixes in). Only the trainer's public surface is used: its constructor, ``train_step()``,
``run_steps()``, ``train()`` and ``final_evaluation()``.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
import time
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, NamedTuple

import torch

from atgs.train.config import ModelConfig, TrainConfig, preset
from atgs.train.trainer import Trainer

if TYPE_CHECKING:
    from atgs.train.trainer import StepResult

NONE: Mapping[str, Any] = MappingProxyType({})  # no overrides

# How a timed run ends (run_timed): without an evaluation (the bench scores the model itself),
# with the trainer's held-out scores after the timed span, or as atgs-train ends (the final
# evaluation writing its images to OUT/eval), inside the timed span.
FINALS = ("none", "scores", "renders")


def ring_scene(cache: Path, *, keyframes: int, test_cameras: int, **synth: Any):
    """The built-in synthetic scene with ``synth`` settings of atgs-synth (preset, frames, cameras,
    width, height; None keeps the default), synthesized and prepared once into ``cache``, with
    ``test_cameras`` cameras spread around its ring held out."""
    from atgs.data.scene import PreparedScene
    from atgs.data.synth.videos import default_config, ensure_default_scene, with_overrides

    cfg = with_overrides(default_config(), **synth)
    scene = PreparedScene.load(ensure_default_scene(cache, cfg, keyframes=keyframes, progress=False))
    n = len(scene.cameras)
    held = sorted({round(i * n / test_cameras) for i in range(test_cameras)})
    return dataclasses.replace(scene, test_cameras=[scene.cameras[i].name for i in held])


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
                  threads: int = 1, device: str = "cpu", progress: bool = False, workers=None) -> Trainer:
    """A fresh Trainer of :func:`case_configs` on ``scene`` writing to ``out`` (emptied first),
    torch's global seed set to the trainer's seed. ``progress``: the set-up's progress bar;
    ``workers``: this process's place among several (atgs.train.distributed.Workers; ``out`` is
    then left as it is)."""
    m, t = case_configs(preset_name, iterations=iterations, minutes=minutes, model=model, train=train,
                        threads=threads)
    if workers is None:  # several workers share ``out``: its caller prepares it (here one would empty it under another)
        shutil.rmtree(out, ignore_errors=True)
    torch.manual_seed(t.seed)
    return Trainer(scene, m, t, out, device=device, progress=progress, workers=workers)


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


def run_worker(cmd: list[str], log_path: Path) -> dict:
    """Run a bench's worker process (stderr to ``log_path``) and return the JSON of its last line."""
    with open(log_path, "w") as log:
        proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=log, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"worker {' '.join(cmd[-6:])} failed (exit {proc.returncode}); see {log_path}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def run_child(cmd: list[str]) -> tuple[dict | None, str]:
    """Run a bench's child process (each case its own, so its peak memory is its own): (the JSON
    of its last stdout line, "") or, when it failed, (None, its stderr)."""
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        return None, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1]), ""


def last_line(text: str) -> str:
    """The last non-empty line of a child's stderr (its error), or "failed"."""
    return text.strip().splitlines()[-1] if text.strip() else "failed"
