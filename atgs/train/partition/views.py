"""Several workers partitioned by views (``--train.partition views``, the default): every worker
holds the whole model, draws every view of a step from the same seeded generator and renders its
contiguous share; after the backward pass they sum their gradients (atgs.train.distributed's
exchange), so every worker applies the one-process update."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import AbstractContextManager

import torch

from atgs.model.atgs_model import ATGSModel
from atgs.train.densify import DensifyStats
from atgs.train.partition.base import DrawView
from atgs.train.partition.workers import SeveralWorkers, shared_views
from atgs.train.step import StepViews, View


class ByViews(SeveralWorkers):
    def describe(self) -> str:
        return "partitioned by views"

    def replicate(self, model: ATGSModel, exposure) -> None:
        tensors = [model.anchor_mu, model.anchor_keyframe, *model.sparse_tensors().values(),
                   *model.decoder.parameters(), model.reach.settled, model.reach.recent]
        self.workers.replicate(tensors + ([exposure.table] if exposure is not None else []))

    def views_of_step(self, n: int, draw: DrawView) -> Iterator[View]:
        return shared_views(self.workers, n, draw)

    def exchange(self, views: StepViews, dense: Sequence[torch.Tensor], model: ATGSModel,
                 asked: Callable[[], bool]) -> bool:
        return self.workers.reduce_step(views, dense, model.sparse_tensors(), model.reach, asked())

    def note_positions(self, stats: DensifyStats, slots: torch.Tensor, stamp: int) -> None:
        self.workers.note_positions(stats, slots, stamp)

    def all_views_statistics(self, stats: DensifyStats, model: ATGSModel) -> AbstractContextManager:
        return self.workers.stats_reduced(stats)

    def own_frames(self, frames, model: ATGSModel) -> list[int]:
        return list(frames)[self.workers.rank::self.workers.world]

    def resumed_statistics(self, state: dict, model: ATGSModel, device: torch.device) -> DensifyStats:
        stats = DensifyStats.from_state(state, device)
        self.workers.own_sums(stats)  # the saved sums are all views': rank 0 carries them on
        return stats
