"""What every partition of several workers does alike (atgs.train.distributed.Workers carries
the collectives): rank 0 leads, its clock sizes the schedule, a stop is agreed at an exchange,
the evaluations are spread over the workers, and the exchange's traffic is reported."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence

from atgs.model.atgs_model import ATGSModel
from atgs.train.distributed import Workers
from atgs.train.partition.base import DrawView, Partition
from atgs.train.step import View


def shared_views(crew: Workers, n: int, draw: DrawView) -> Iterator[View]:
    """Workers that share a step's views (the ``crew``) draw all ``n`` of them, backgrounds
    included, in one process's order (each keeps the same generator); each yields its share."""
    drawn = [draw(v, True) for v in range(n)]
    for v in crew.share(n):
        yield drawn[v]


class SeveralWorkers(Partition):
    def __init__(self, workers: Workers) -> None:
        self.workers = workers

    def checkpoint_share(self, path, mapped: dict) -> tuple[dict, range | None]:
        return mapped, None  # (memory-mapped: a worker reads only the rows it keeps)

    def stop_requested(self, asked: Callable[[], bool], agreed: bool) -> bool:
        return agreed

    def agreed_floats(self, values: Sequence[float]) -> list[float]:
        return self.workers.broadcast_floats(values)

    def evaluation_share(self, frames: Sequence[int], model: ATGSModel):
        from atgs.eval.evaluate import Share

        return Share(self.own_frames(frames, model), self.workers.gather_to_leader)

    def on_every_worker(self, ev: dict | None, on_test_cameras: bool) -> dict:
        """Each worker scored its share of the frames; rank 0 took the mean over all views, as one
        process does."""
        keys = ("psnr", "psnr_matched", "ssim", "views")
        mine = [0.0] * len(keys) if ev is None else [float(ev[k]) for k in keys]
        got = dict(zip(keys, self.workers.broadcast_floats(mine)))
        return {**got, "views": int(got["views"]), "on_test_cameras": on_test_cameras}

    def summary(self) -> dict | None:
        return self.workers.traffic.summary(self.workers.world)
