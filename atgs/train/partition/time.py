"""Several workers partitioned by time (``--train.partition time``): each worker holds a
contiguous block of the model's time segments and the anchors its frames reach
(atgs.train.partition.time_slice), and draws its views from its own frames with a generator of
its own.

After the backward pass the workers reduce only what is shared (:data:`EXCHANGED`: the spatial
grid's touched rows and the shared anchors' rows through atgs.train.distributed's sparse exchange,
the decoder's and the exposure's dense gradients through its all-reduce) and average it; the owned
tables never leave their worker.

Densification: each worker grows and prunes its own anchors from its own statistics and
generator; the shared anchors' statistics are summed over the workers and every worker grows them
with the same generator (seeded by the step) and prunes them alike, so they stay replicas. A new
anchor takes its parent's keyframe, so it is shared or own as its parent.

Checkpoints: rank 0 writes every worker's part into one ``ckpt.pt`` in the usual format; a
resume reads only this worker's segments' rows of it and keeps its anchors (any number of
workers, and any partition, resume from any checkpoint)."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import AbstractContextManager, ExitStack
from pathlib import Path

import torch

from atgs.model.atgs_model import ANCHOR_TABLES, ATGSModel
from atgs.train.config import DensifyConfig
from atgs.train.densify import DensifyStats, grow_anchors
from atgs.train.distributed import Workers, time_group_of
from atgs.train.optim import SparseAdam
from atgs.train.partition.base import DrawView
from atgs.train.partition.time_slice import (TimeSlice, fill_payload, held_anchors_of_state, local_part,
                                             read_segment_rows, segment_block)
from atgs.train.partition.workers import SeveralWorkers
from atgs.train.step import StepViews, View

# the sparse tables whose gradients the workers reduce: every row, or the shared anchors' rows
EXCHANGED = {"spatial": "all", **{name: "shared" for name in ANCHOR_TABLES}}


def keep_owned(views: StepViews, num_shared: int) -> StepViews:
    """Take the owned gradients (segment tables, own anchors' rows) and the reach of the own
    anchors out of ``views`` before the exchange, which then carries only the shared ones;
    returns the owned ones (what a time group's workers exchange among themselves, partitioned
    by both: atgs.train.partition.both.reduce_owned)."""
    exchanged, owned = {}, {}
    for name, parts in views.grads.items():
        kind = EXCHANGED.get(name)
        if kind == "all":
            exchanged[name] = parts
        elif kind == "shared":
            for rows, g in parts:
                mask = rows < num_shared
                exchanged.setdefault(name, []).append((rows[mask], g[mask]))
                owned.setdefault(name, []).append((rows[~mask], g[~mask]))
        else:
            owned[name] = parts
    views.grads = exchanged
    own_decoded = [ids[ids >= num_shared] for ids in views.decoded]
    views.decoded = [ids[ids < num_shared] for ids in views.decoded]  # the reach of the shared anchors
    return StepViews(grads=owned, decoded=own_decoded, bad=views.bad)


def with_owned(views: StepViews, owned: StepViews, groups: int, dense: Sequence[torch.Tensor]) -> None:
    """After the exchange: the shared gradients (summed over the workers: over the ``groups``
    time groups' views) become their mean over the groups, and the owned ones join them."""
    if views.bad or owned.bad:
        views.bad = True
        return
    for p in dense:
        if p.grad is not None:
            p.grad.div_(groups)
    views.grads = {name: [(rows, g / groups) for rows, g in parts] for name, parts in views.grads.items()}
    for name, parts in owned.grads.items():
        views.grads.setdefault(name, []).extend(parts)


class ByTime(SeveralWorkers):
    """One time group per worker (and the base of :class:`atgs.train.partition.both.ByBoth`,
    whose time groups have several)."""

    def __init__(self, workers: Workers, groups: int) -> None:
        super().__init__(workers)
        self.time_groups = groups
        self.time_rank = time_group_of(workers.rank, workers.world, groups)
        self.part: TimeSlice | None = None  # this worker's share, planned with the model
        self._taken: torch.Tensor | None = None  # the anchors of the given model it kept

    def describe(self) -> str:
        return "partitioned by time"

    # --- the model -------------------------------------------------------------------------------
    def new_model_segments(self, num_segments: int) -> range:
        return segment_block(num_segments, self.time_rank, self.time_groups)

    def take_share(self, model: ATGSModel, measure_velocities: Callable[[], None]) -> None:
        """The anchors' start (rank 0's, velocities included) on every worker, then this worker's
        share of them (and of a given whole model's segments)."""
        measure_velocities()
        self.workers.replicate([model.anchor_mu, model.anchor_keyframe, *(getattr(model, n) for n in ANCHOR_TABLES),
                                model.spatial.table, *model.decoder.parameters()])
        self.part = TimeSlice.plan(model.timeline, model, self.time_rank, self.time_groups)
        self._taken = self.part.take_model(model)

    def held_optimizer_state(self, state: dict | None) -> dict | None:
        return None if state is None else held_anchors_of_state(state, self._taken)

    def held_segments(self) -> range:
        return self.part.segments

    def segment_visits(self, grid_visits: torch.Tensor) -> torch.Tensor:
        return grid_visits[self.part.segments.start:self.part.segments.stop]

    def replicate(self, model: ATGSModel, exposure) -> None:
        if exposure is not None:  # (the model's shared parts with its share: take_share)
            self.workers.replicate([exposure.table])

    def _shared_anchors(self, model: ATGSModel) -> range:
        return range(self.part.num_shared(model))

    def _own_anchors(self, model: ATGSModel) -> range:
        return range(self.part.num_shared(model), model.num_anchors)

    # --- a step ----------------------------------------------------------------------------------
    def views_of_step(self, n: int, draw: DrawView) -> Iterator[View]:
        for v in range(n):  # its own, as one process draws them
            yield draw(v, False)

    def exchange(self, views: StepViews, dense: Sequence[torch.Tensor], model: ATGSModel,
                 asked: Callable[[], bool]) -> bool:
        """Only the shared parameters' gradients travel among all workers."""
        owned = keep_owned(views, self.part.num_shared(model))
        tables = {n: t for n, t in model.sparse_tensors().items() if n in EXCHANGED}
        stop = self.workers.reduce_step(views, dense, tables, model.reach, asked())
        with_owned(views, self._owned_of_group(owned, model), self.time_groups, dense)
        return stop

    def _owned_of_group(self, owned: StepViews, model: ATGSModel) -> StepViews:
        """The owned gradients of the time group (one worker: its own)."""
        return owned

    def note_positions(self, stats: DensifyStats, slots: torch.Tensor, stamp: int) -> None:
        # every time group renders views of that index
        self.workers.note_positions(stats, slots, stamp * self.time_groups + self.time_rank)

    def all_views_statistics(self, stats: DensifyStats, model: ATGSModel) -> AbstractContextManager:
        """The shared anchors' statistics summed among all workers."""
        both = ExitStack()
        both.enter_context(self.workers.stats_reduced(stats, lambda: self._shared_anchors(model)))
        return both

    def grow(self, model: ATGSModel, stats: DensifyStats, cfg: DensifyConfig, opt: SparseAdam,
             generator: torch.Generator, seed: int, step: int) -> None:
        """The shared anchors grow alike on every worker (summed statistics, a generator seeded by
        the step), each worker's own from its own; then shared first again."""
        n = self.part.num_shared(model)
        same = torch.Generator(device="cpu").manual_seed(seed * 1_000_003 + step)
        grow_anchors(model, stats, cfg, opt, same, growing=range(0, n), room=cfg.max_anchors - n)
        grow_anchors(model, stats, cfg, opt, generator, growing=range(n, model.num_anchors))
        self.part.reorder(model, stats, opt)

    # --- evaluation ------------------------------------------------------------------------------
    def own_frames(self, frames: Sequence[int], model: ATGSModel) -> list[int]:
        """The frames its model decodes (each frame is one worker's)."""
        return [f for f in frames if f in model.decodable_frames]

    # --- checkpoints -----------------------------------------------------------------------------
    def payload(self, make: Callable[[], dict], model: ATGSModel, opt: SparseAdam, stats: DensifyStats,
                grid_visits: torch.Tensor) -> dict | None:
        """Rank 0 writes every worker's part, received as the file is written."""
        parts = self.workers.rows_to_leader(local_part(model, opt, stats, grid_visits, self.part,
                                                       replica=self._replica()))
        return fill_payload(make(), parts) if self.leads else None

    def _replica(self) -> bool:
        """It holds what another worker sends (partitioned by both)."""
        return False

    def checkpoint_share(self, path: str | Path, mapped: dict) -> tuple[dict, range]:
        """This worker's segments' rows only (the others are never read)."""
        segments = segment_block(int(mapped["model"]["num_segments"]), self.time_rank, self.time_groups)
        read_segment_rows(path, mapped, segments)
        return mapped, segments

    def resumed_statistics(self, state: dict, model: ATGSModel, device: torch.device) -> DensifyStats:
        """This worker's share of the whole state; the shared anchors' sums carried on by rank 0."""
        stats = DensifyStats.from_state(state, device)
        stats.keep(self._taken, model.cfg.gaussians_per_anchor)
        self.workers.own_sums(stats, self._shared_anchors(model))
        return stats

    def resume_generator(self, gen: torch.Generator, state: torch.Tensor, seed: int, step: int) -> None:
        """The first time group's is the run's; the others draw from a seed of their own."""
        if self.time_rank == 0:
            gen.set_state(state)
        else:
            gen.manual_seed(seed + 7919 * self.time_rank + step)
