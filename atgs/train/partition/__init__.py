"""How a run is split among processes: one strategy object per partition behind one interface
(:class:`~atgs.train.partition.base.Partition`), which the trainer calls instead of asking whether
it has workers.

- :class:`~.single.OneProcess`: one process;
- :class:`~.views.ByViews`: several workers share each step's views (``--train.partition views``);
- :class:`~.time.ByTime`: each worker holds a block of time segments (``--train.partition time``);
- :class:`~.both.ByBoth`: time groups of workers that share their steps' views (``--train.partition both``)."""

from __future__ import annotations

from atgs.train.config import TrainConfig
from atgs.train.distributed import Workers, check_settings, time_groups_of
from atgs.train.partition.base import Partition
from atgs.train.partition.both import ByBoth
from atgs.train.partition.single import OneProcess
from atgs.train.partition.time import ByTime
from atgs.train.partition.views import ByViews

__all__ = ["ByBoth", "ByTime", "ByViews", "OneProcess", "Partition", "partition_of"]


def partition_of(workers: Workers | None, cfg: TrainConfig) -> Partition:
    """This process's partition of a run with ``cfg``'s settings on ``workers`` (None: one
    process); refuses settings the workers cannot train (one line). Collective with workers."""
    if workers is None:
        return OneProcess()
    check_settings(cfg.views_per_step, workers.world, cfg.partition, cfg.time_groups, workers.nodes)
    groups = time_groups_of(cfg.partition, workers.world, cfg.time_groups, workers.nodes)
    if groups == 1:
        return ByViews(workers)
    if groups == workers.world:
        return ByTime(workers, groups)
    return ByBoth(workers, groups)
