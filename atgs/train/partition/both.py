"""Several workers partitioned by both (``--train.partition both``): the workers form time groups
of consecutive ranks (``--train.time-groups``, by default one per node), and each group holds one
block as one worker of the time partition does (:class:`~atgs.train.partition.time.ByTime`). Its
workers (its *crew*, ``Workers.crew``) hold the same share and draw the same views from the
group's generator, each renders its share of them (as the views partition shares a step), and they
sum their owned gradients and own anchors' reach and statistics among themselves
(:func:`reduce_owned`), while the shared ones are reduced among all workers and averaged over the
groups. So the run equals the time partition with one worker per group
(tests/test_distributed_both.py), and only the shared rows cross between groups (between nodes,
with one group per node)."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import AbstractContextManager

import torch

from atgs.model.atgs_model import ATGSModel
from atgs.geometry.reach import AnchorReach
from atgs.train.densify import DensifyStats
from atgs.train.distributed import Workers
from atgs.train.partition.base import DrawView
from atgs.train.partition.time import EXCHANGED, ByTime
from atgs.train.partition.workers import shared_views
from atgs.train.step import StepViews, View


def reduce_owned(crew: Workers, owned: StepViews, tables: dict[str, torch.Tensor], reach: AnchorReach) -> StepViews:
    """The owned gradients and reach of a time group's workers, who render shares of the same
    views, summed among them (the crew's sparse exchange; the shared ones travel among all
    workers). ``tables``: the model's sparse tables by name."""
    crew.reduce_step(owned, [], {n: t for n, t in tables.items() if EXCHANGED.get(n) != "all"}, reach, False)
    return owned


class ByBoth(ByTime):
    def __init__(self, workers: Workers, groups: int) -> None:
        super().__init__(workers, groups)
        self.crew = workers.crew(workers.world // groups)  # (collective: every worker creates every crew)

    def describe(self) -> str:
        return f"partitioned by both: {self.time_groups} time groups of {self.workers.world // self.time_groups}"

    def views_of_step(self, n: int, draw: DrawView) -> Iterator[View]:
        return shared_views(self.crew, n, draw)

    def _owned_of_group(self, owned: StepViews, model: ATGSModel) -> StepViews:
        return reduce_owned(self.crew, owned, model.sparse_tensors(), model.reach)

    def note_positions(self, stats: DensifyStats, slots: torch.Tensor, stamp: int) -> None:
        super().note_positions(stats, slots, stamp)
        self.crew.note_positions(stats, slots, stamp * self.time_groups + self.time_rank)

    def all_views_statistics(self, stats: DensifyStats, model: ATGSModel) -> AbstractContextManager:
        """Also the own anchors' statistics, summed within the time group."""
        both = super().all_views_statistics(stats, model)
        both.enter_context(self.crew.stats_reduced(stats, lambda: self._own_anchors(model)))
        return both

    def own_frames(self, frames: Sequence[int], model: ATGSModel) -> list[int]:
        """The time group's frames, split among its workers."""
        return super().own_frames(frames, model)[self.crew.rank::self.crew.world]

    def _replica(self) -> bool:
        return self.crew.rank > 0  # (the group's first sends what they all hold)

    def resumed_statistics(self, state: dict, model: ATGSModel, device: torch.device) -> DensifyStats:
        stats = super().resumed_statistics(state, model, device)
        self.crew.own_sums(stats, self._own_anchors(model))  # (the group's first carries its own anchors' on)
        return stats

    def summary(self) -> dict | None:
        out = super().summary()
        out["time_group"] = self.crew.traffic.summary(self.crew.world)
        return out
