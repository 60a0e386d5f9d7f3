"""A worker's share of the model partitioned by time (``--train.partition time``, or a time
group's by both; the strategies: atgs.train.partition.time and .both): a contiguous block of the
model's time segments.

A worker holds, of the model (docs/training.md, "Several workers"):

- its segments' rows of the per-segment tables (the 4D hash grids and the temporal MLPs,
  ``SEGMENT_TABLES``), queried by local index (``ATGSModel.first_segment``);
- the anchors whose keyframe windows touch its segments' frames: *own* anchors, whose keyframe
  only its frames reach, and *shared* ones: static anchors, and those of keyframes that the
  frames of two or more workers reach (boundary keyframes). Shared anchors are replicated on
  every worker, in the same order, before the own ones (the anchor tables' first rows);
- the parameters every frame uses: the spatial grid, the decoder, the camera exposure.

Checkpoints: rank 0 writes every worker's part (:func:`local_part`: its own anchors, segment
rows, their optimizer state and statistics), received piece by piece as it writes, into one
``ckpt.pt`` in the usual format (the anchors shared first, then each worker's own ones in rank
order; the segments in order; a time group's other workers send nothing); any number of workers,
and any partition, resume from it (:func:`read_segment_rows`, :meth:`TimeSlice.take_model`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from atgs.config_checks import ConfigError
from atgs.io.torch_zip import Streamed, read_rows
from atgs.model.anchors import STATIC
from atgs.model.atgs_model import ANCHOR_TABLES, SEGMENT_TABLES, ATGSModel, segment_rows
from atgs.timeline import Timeline
from atgs.train.densify import DensifyStats
from atgs.train.optim import SparseAdam


def segment_block(num_segments: int, rank: int, world: int) -> range:
    """Worker ``rank``'s contiguous block of ``num_segments`` segments."""
    if num_segments < world:
        raise ConfigError(f"--train.partition time / both gives each of {world} workers (or time groups) whole "
                          f"time segments, but the model has {num_segments}; pass --model.num-segments {world} "
                          "(or more) or --train.partition views")
    return range(num_segments * rank // world, num_segments * (rank + 1) // world)


@dataclass
class TimeSlice:
    """This worker's share of the model: its segments and which anchors it holds."""

    rank: int
    world: int
    segments: range
    held_keyframes: torch.Tensor  # (K + 1,) bool: keyframes whose anchors it holds; the last: static
    shared_keyframes: torch.Tensor  # (K + 1,) bool: keyframes several workers hold; the last: static

    @classmethod
    def plan(cls, timeline: Timeline, model: ATGSModel, rank: int, world: int) -> "TimeSlice":
        K = timeline.num_keyframes
        touched = torch.zeros(world, K + 1, dtype=torch.bool, device="cpu")
        touched[:, K] = True  # static anchors: every frame
        for r in range(world):
            segs = segment_block(timeline.num_segments, r, world)
            frames = range(timeline.frames_of_segment(segs.start).start,
                           timeline.frames_of_segment(segs.stop - 1).stop)
            if not frames:
                raise ConfigError(f"worker {r}'s time segments {segs.start}..{segs.stop - 1} hold no frame; "
                                  "pass fewer --model.num-segments or fewer workers")
            # windows move monotonically with the frame: the first and last frames bound them
            lo, hi = timeline.window_of_frame(frames.start)[0], timeline.window_of_frame(frames.stop - 1)[1]
            touched[r, lo:hi + 1] = True
        if model.cfg.static_keyframe0 and model.cfg.anchor_layout == "per-keyframe":
            touched[:, 0] = True  # keyframe 0's anchors are active at every frame
        return cls(rank, world, segment_block(timeline.num_segments, rank, world), touched[rank],
                   touched.sum(0) > 1)

    @staticmethod
    def _of(table: torch.Tensor, keyframe: torch.Tensor) -> torch.Tensor:
        k = torch.where(keyframe == STATIC, table.numel() - 1, keyframe).cpu()
        return table[k].to(keyframe.device)

    def shared(self, keyframe: torch.Tensor) -> torch.Tensor:
        """(A,) bool: anchors of these keyframes every worker holds."""
        return self._of(self.shared_keyframes, keyframe)

    def order(self, keyframe: torch.Tensor) -> torch.Tensor:
        """Indices of the anchors (of a whole model's ``keyframe``) this worker holds: the shared
        ones first, then its own, each in the given order."""
        held, shared = self._of(self.held_keyframes, keyframe), self.shared(keyframe)
        return torch.cat([shared.nonzero().squeeze(1), (held & ~shared).nonzero().squeeze(1)])

    def num_shared(self, model: ATGSModel) -> int:
        """How many of the model's first anchors are the shared ones."""
        return int(self.shared(model.anchor_keyframe).sum())

    def frames(self, timeline: Timeline) -> range:
        return range(timeline.frames_of_segment(self.segments.start).start,
                     timeline.frames_of_segment(self.segments.stop - 1).stop)

    # --- slicing a whole model's state ------------------------------------------------------------
    def take_model(self, model: ATGSModel) -> torch.Tensor:
        """Keep this worker's anchors of a model of its segments (built with them, or loaded
        with ``ATGSModel.from_state(segments=...)``); returns the indices of the anchors kept."""
        if model.hash.num_grids != len(self.segments) or model.first_segment != self.segments.start:
            raise AssertionError("the model holds other segments than this worker's")
        ids = self.order(model.anchor_keyframe)
        model.keep_anchors(ids)
        return ids  # (the optimizer state: held_anchors_of_state; the statistics: DensifyStats.keep)

    def reorder(self, model: ATGSModel, stats, opt) -> None:
        """Put the shared anchors first again (after growth appended some)."""
        perm = torch.argsort((~self.shared(model.anchor_keyframe)).to(torch.int8), stable=True)
        if bool((perm == torch.arange(perm.numel(), device=perm.device)).all()):
            return
        model.keep_anchors(perm)
        stats.keep(perm, model.cfg.gaussians_per_anchor)
        for name in ANCHOR_TABLES:
            opt.keep_rows(name, perm)


def held_anchors_of_state(sparse_opt: dict, ids: torch.Tensor) -> dict:
    """A whole model's sparse optimizer state with only the rows of the anchors ``ids`` (of
    :meth:`TimeSlice.take_model`) in the anchor tables."""
    return SparseAdam.rows_of_state(sparse_opt, ANCHOR_TABLES, ids)


def read_segment_rows(path, data: dict, segments: range) -> None:
    """Put in ``data`` (a memory-mapped checkpoint of all segments, ``path``'s) only
    ``segments``' rows of the per-segment tables and of their optimizer state, read from the
    file (atgs.io.torch_zip.read_rows: nothing of the other segments is read)."""
    num = int(data["model"]["num_segments"])
    per_grid = data["model"]["hash"].shape[0] // num
    wanted = {("model", name): segment_rows(name, segments, per_grid) for name in SEGMENT_TABLES}
    wanted.update({("trainer", "sparse_opt", *where): segment_rows(name, segments, per_grid)
                   for name in SEGMENT_TABLES for where in SparseAdam.state_paths(name)})
    read_rows(path, data, wanted)


# --- checkpoints -------------------------------------------------------------------------------------------
def local_part(model: ATGSModel, opt: SparseAdam, stats: DensifyStats, grid_visits: torch.Tensor,
               part: TimeSlice, replica: bool = False) -> dict[str, torch.Tensor]:
    """What this worker adds to the gathered checkpoint, each tensor to be concatenated in rank
    order, by its path in the checkpoint's payload: its anchors (rank 0: the shared ones too),
    its segments' rows, their optimizer state, statistics and visit counts. ``replica``: a time
    group's worker other than its first (partitioned by both), which holds the same as that one:
    nothing (rows of none)."""
    a = 0 if part.rank == 0 else part.num_shared(model)
    tables = model.sparse_tensors()
    out = {"model/anchor_mu": model.anchor_mu[a:], "model/anchor_keyframe": model.anchor_keyframe[a:]}
    for name in (*ANCHOR_TABLES, *SEGMENT_TABLES):
        first = a if name in ANCHOR_TABLES else 0
        out[f"model/{name}"] = tables[name][first:]
        out.update({f"trainer/sparse_opt/{key}/{name}": rows for key, rows in opt.rows_from(name, first).items()})
    out.update({f"trainer/densify/{name}": rows for name, rows in stats.rows_from(a).items()})
    out["trainer/grid_visits"] = grid_visits[part.segments.start:part.segments.stop]
    return {k: (v[:0] if replica else v).detach().cpu() for k, v in out.items()}


def fill_payload(payload: dict, gathered: dict[str, Streamed]) -> dict:
    """Rank 0's checkpoint payload with the workers' parts (:func:`local_part`, concatenated in
    rank order as ``Workers.rows_to_leader`` streams them into the file) in place of its own."""
    for path, whole in gathered.items():
        *where, name = path.split("/")
        node = payload
        for key in where:
            node = node[key]
        node[name] = whole
    return payload
