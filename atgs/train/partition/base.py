"""What a partition decides for the trainer (atgs.train.trainer): one interface, one object per
way of training a run: one process (:mod:`.single`), several workers partitioned by views
(:mod:`.views`), by time (:mod:`.time`) or by both (:mod:`.both`).

The trainer asks it which views a step draws, what is exchanged after the backward pass, whose
densification statistics the growth reads, which frames an evaluation scores, how a checkpoint
is written and how a checkpoint is sliced on resume. It holds no other notion of workers."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from contextlib import AbstractContextManager
from pathlib import Path

import torch

from atgs.checkpoint import read_checkpoint
from atgs.model.atgs_model import ATGSModel
from atgs.train.config import DensifyConfig
from atgs.train.densify import DensifyStats, grow_anchors
from atgs.train.distributed import Workers
from atgs.train.optim import SparseAdam
from atgs.train.step import StepViews, View

# a step's view v drawn from the run's generator; ``ahead``: its random backgrounds too
DrawView = Callable[[int, bool], View]


class Partition(ABC):
    """How this process takes part in the run. Methods that say "collective" are called by every
    worker in the same order."""

    workers: Workers | None = None  # this process among the run's workers; None: one process
    time_rank: int = 0  # its time group (each draws its own views, from its own generator)
    time_groups: int = 1  # blocks of time segments the run is split into

    @property
    def leads(self) -> bool:
        """This process prints, evaluates and writes the run's files."""
        return self.workers is None or self.workers.leads

    @abstractmethod
    def describe(self) -> str:
        """How the run is split, for the start-up line ("" for one process)."""

    def draw_seed(self, seed: int) -> int:
        """The seed of this process's generator (each time group's own; the first's is the run's)."""
        return seed + 7919 * self.time_rank

    # --- the model -------------------------------------------------------------------------------
    def new_model_segments(self, num_segments: int) -> range | None:
        """The time segments a new model holds here; None: all of them."""
        return None

    def take_share(self, model: ATGSModel, measure_velocities: Callable[[], None]) -> None:
        """Keep this process's share of ``model`` (new, or loaded with :meth:`read_checkpoint`'s
        segments); ``measure_velocities``: a new model's start from optical flow, measured here by
        a partition that needs it before it slices (collective)."""

    def held_optimizer_state(self, state: dict | None) -> dict | None:
        """The sparse optimizer state of the rows this process kept of a whole model's."""
        return state

    def held_segments(self) -> range | None:
        """The segments this process draws views from; None: all."""
        return None

    def segment_visits(self, grid_visits: torch.Tensor) -> torch.Tensor:
        """Of the run's per-segment visit counts, those of the segments this process holds."""
        return grid_visits

    @abstractmethod
    def replicate(self, model: ATGSModel, exposure) -> None:
        """Every worker starts from rank 0's parameters that it holds too (collective)."""

    # --- a step ----------------------------------------------------------------------------------
    @abstractmethod
    def views_of_step(self, n: int, draw: DrawView) -> Iterator[View]:
        """The step's ``n`` views that this process renders, drawn by ``draw`` in the order one
        process draws them (so the generator stays the same on every worker)."""

    @abstractmethod
    def exchange(self, views: StepViews, dense: Sequence[torch.Tensor], model: ATGSModel,
                 asked: Callable[[], bool]) -> bool:
        """After the backward pass: put the other workers' share of the step into ``views`` and
        the ``dense`` parameters' gradients. ``asked``: whether a stop was asked here. Returns
        whether any worker asked (collective)."""

    @abstractmethod
    def stop_requested(self, asked: Callable[[], bool], agreed: bool) -> bool:
        """Whether the run stops before the next step: one process polls ``asked``; several
        workers stop after the step at whose exchange any asked (``agreed``)."""

    def note_positions(self, stats: DensifyStats, slots: torch.Tensor, stamp: int) -> None:
        """Slots whose last position the view ``stamp`` (step * views + view) just wrote."""

    @abstractmethod
    def all_views_statistics(self, stats: DensifyStats, model: ATGSModel) -> AbstractContextManager:
        """Inside: ``stats`` hold every view's statistics so far (growth, pruning and checkpoints
        read them; collective)."""

    def grow(self, model: ATGSModel, stats: DensifyStats, cfg: DensifyConfig, opt: SparseAdam,
             generator: torch.Generator, seed: int, step: int) -> None:
        """Grow anchors from the statistics (inside :meth:`all_views_statistics`)."""
        grow_anchors(model, stats, cfg, opt, generator)

    def agreed_floats(self, values: Sequence[float]) -> list[float]:
        """Rank 0's ``values`` (its clock: every worker sizes the same schedule; collective)."""
        return list(values)

    # --- evaluation ------------------------------------------------------------------------------
    def own_frames(self, frames: Sequence[int], model: ATGSModel) -> list[int]:
        """This process's share of an evaluation's ``frames``."""
        return list(frames)

    def evaluation_share(self, frames: Sequence[int], model: ATGSModel):
        """An evaluation spread over the workers (atgs.eval.evaluate.Share); None: all here."""
        return None

    def on_every_worker(self, ev: dict | None, on_test_cameras: bool) -> dict:
        """A spread evaluation's figures (rank 0's; None elsewhere) on every worker (collective)."""
        return ev

    # --- checkpoints -----------------------------------------------------------------------------
    def payload(self, make: Callable[[], dict], model: ATGSModel, opt: SparseAdam, stats: DensifyStats,
                grid_visits: torch.Tensor) -> dict | None:
        """The checkpoint's payload (``make()``: this process's own), gathered from the workers
        where each holds a part of it; None on a worker that does not write (collective)."""
        return make() if self.leads else None

    def checkpoint_share(self, path: str | Path, mapped: dict) -> tuple[dict, range | None]:
        """What this process loads of the checkpoint ``path`` to resume (``mapped``: read
        memory-mapped): (its data, the time segments of its model or None for all)."""
        return read_checkpoint(path), None  # (one process: read whole)

    def resumed_statistics(self, state: dict, model: ATGSModel, device: torch.device) -> DensifyStats:
        """A whole run's saved statistics, as this process carries them on."""
        return DensifyStats.from_state(state, device)

    def resume_generator(self, gen: torch.Generator, state: torch.Tensor, seed: int, step: int) -> None:
        """The generator of a resumed run."""
        gen.set_state(state)

    def summary(self) -> dict | None:
        """What the workers exchanged (the run's result), None for one process."""
        return None
