"""One process trains the run: it draws and renders every view of a step and exchanges nothing."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import AbstractContextManager, nullcontext

import torch

from atgs.model.atgs_model import ATGSModel
from atgs.train.densify import DensifyStats
from atgs.train.partition.base import DrawView, Partition
from atgs.train.step import StepViews, View


class OneProcess(Partition):
    def describe(self) -> str:
        return ""

    def replicate(self, model: ATGSModel, exposure) -> None:
        pass

    def views_of_step(self, n: int, draw: DrawView) -> Iterator[View]:
        # lazily: each camera's random background is drawn as it renders (after the view's draw)
        for v in range(n):
            yield draw(v, False)

    def exchange(self, views: StepViews, dense: Sequence[torch.Tensor], model: ATGSModel,
                 asked: Callable[[], bool]) -> bool:
        return False

    def stop_requested(self, asked: Callable[[], bool], agreed: bool) -> bool:
        return asked()

    def all_views_statistics(self, stats: DensifyStats, model: ATGSModel) -> AbstractContextManager:
        return nullcontext()
