"""Training on several workers: data parallel over each step's views, through torch.distributed.

Launch: ``torchrun --nproc-per-node N -m atgs.cli.train ...`` or ``atgs-train --workers N`` (which
runs torchrun's launcher in-process, atgs.cli.train); the workers meet through torch's env://
rendezvous (RANK, WORLD_SIZE, MASTER_ADDR, MASTER_PORT, set by torchrun). gloo on the CPU, NCCL on
CUDA when every worker has a GPU of its own (else gloo through host memory: NCCL refuses two
workers on one GPU). A :class:`Workers` is this process's place among them and carries the
collectives; how a run uses them is its partition's (atgs.train.partition: one process trains
without one, ``Trainer(workers=None)``).

What a step does on N workers (docs/training.md, "Several workers"):

- every worker draws the whole step's views from the same seeded generator (the sampler and the
  random backgrounds; every later draw then stays the same too) and renders its contiguous share;
- each view's loss is divided by the step's *global* number of renders, so the sum of the workers'
  gradients is the one-process gradient;
- one all-reduce (sum) carries the decoder's and the exposure's dense gradients, the step's flags
  (a non-finite view skips the step on every worker; Ctrl-C stops all after the same step), the
  losses for the log and the row counts of the sparse part;
- one all-gather carries the sparse part: per table the rows this worker's views touched and their
  gradients (merged over its views), and the reach (atgs.geometry.reach) its decodes measured;
  every worker merges them in rank order, so all apply the same update to the same rows;
- densification statistics stay per worker between densifications (sums; the last position is the
  latest view's) and are reduced when densification, the final pruning or a checkpoint reads them;
  growing and pruning then run on every worker from the same statistics and the same generator.

So every worker holds the same model, rank 0 writes the checkpoint, and a checkpoint resumes on any
number of workers. Partitioned by time or by both (atgs.train.partition), the same exchange
carries only what every worker holds, and a time group's workers (a :meth:`Workers.crew`, a
process group of their own) run it among themselves for what their group owns.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from functools import partial
from datetime import timedelta
import math
import os
import re
import time

import torch
import torch.distributed as dist

from atgs.config_checks import ConfigError
from atgs.errors import UserError
from atgs.io.torch_zip import Streamed
from atgs.geometry.reach import AnchorReach
from atgs.train.optim import merge_rows
from atgs.train.step import StepViews

_HEADER = 6  # bad, stop, loss sum, PSNR sum, renders, Gaussians rendered
REACH = "reach"  # the sparse part's last item: anchors' reach, reduced by max
_EXACT = 2**24  # counts travel as float32: exact below this


class WorkerLost(UserError, RuntimeError):
    """Another worker failed, was stopped or stopped answering (one line; the last checkpoint
    resumes)."""


def time_groups_of(partition: str, workers: int, asked: int = 0, nodes: int = 1) -> int:
    """How many blocks of time segments ``workers`` workers split the model into: none for the
    views partition (1: everyone holds all), one per worker for the time partition, and for both
    at once ``asked`` (--train.time-groups; 0: one per node, torchrun's --nnodes), each block's
    views shared by ``workers / groups`` workers (atgs.train.partition.time_slice)."""
    if partition == "views" or workers <= 1:
        return 1
    if partition == "time":
        return workers
    groups = asked or nodes
    if groups < 2 or workers % groups:
        what = (f"--train.time-groups {asked}" if asked
                else f"one time group per node ({nodes} node{'s' * (nodes != 1)})")
        raise ConfigError(f"--train.partition both splits {workers} workers into time groups of equal size, but "
                          f"{what} does not; pass --train.time-groups G with G >= 2 dividing {workers}, or "
                          "--train.partition views / time")
    return groups


def time_group_of(rank: int, workers: int, groups: int) -> int:
    """The time group of worker ``rank``: groups are runs of consecutive ranks (:meth:`Workers.crew`)."""
    return rank // (workers // groups)


def sharing_workers(workers: int, partition: str = "views", time_groups: int = 0, nodes: int = 1) -> int:
    """How many workers share each step's views: all of them partitioned by views, a time
    group's partitioned by both, one partitioned by time (each draws its own)."""
    return workers // time_groups_of(partition, workers, time_groups, nodes) if workers > 1 else 1


def check_settings(views_per_step: int, workers: int, partition: str = "views", time_groups: int = 0,
                   nodes: int = 1) -> None:
    """Refuse settings that N workers cannot train as one process would: the workers that share a
    step's views (:func:`sharing_workers`) need one view each at least."""
    sharing = sharing_workers(workers, partition, time_groups, nodes)
    if views_per_step < sharing:
        who = f"{sharing} workers" if sharing == workers else f"the {sharing} workers of each time group"
        raise ConfigError(f"{who} share each step's views, but --train.views-per-step is "
                          f"{views_per_step}; pass --train.views-per-step {sharing} (or a multiple of it)")


def views_that_work(views_per_step: int, workers: int, partition: str = "views", time_groups: int = 0,
                    nodes: int = 1) -> int:
    """The views per step of a run whose --train.views-per-step was not given: the preset's, or
    the fewest that the workers sharing a step can split (one each) when the preset's are fewer."""
    return max(views_per_step, sharing_workers(workers, partition, time_groups, nodes))


@dataclass
class Traffic:
    """Bytes this worker puts into the collectives (payloads; a ring all-reduce moves about twice
    its payload per worker, an all-gather receives N - 1 payloads)."""

    steps: int = 0
    dense: int = 0  # the step's all-reduce (dense gradients, flags, counts)
    sparse: int = 0  # the step's all-gather (touched rows and their gradients, reach), padded
    sparse_rows: int = 0  # rows of all tables this worker sent
    statistics: int = 0  # densification statistics, when densification or a checkpoint reads them
    tables: int = 0  # what a dense all-reduce of every sparse table would carry per step (last step)
    seconds: float = 0.0  # in the step's exchange: packing, the two collectives (waiting included), merging

    def summary(self, world: int) -> dict:
        n = max(1, self.steps)
        return {"workers": world, "steps": self.steps,
                "dense_bytes_per_step": self.dense / n, "sparse_bytes_per_step": self.sparse / n,
                "sparse_rows_per_step": self.sparse_rows / n, "statistics_bytes_per_step": self.statistics / n,
                "dense_tables_bytes_per_step": float(self.tables), "exchange_seconds_per_step": self.seconds / n}


def _reason(error: BaseException) -> str:
    """The gist of a collective's error: its first sentence, without the source location."""
    text = re.sub(r"\[[^\]]*\.(cc|cpp|h):\d+\]\s*", "", " ".join(str(error).split()))
    return text.split(". ")[0][:160] or type(error).__name__


def _backend(device: torch.device, local_world: int) -> str:
    if device.type == "cuda" and dist.is_nccl_available() and torch.cuda.device_count() >= local_world:
        return "nccl"
    return "gloo"


def _attempt_store(rank: int, world: int, timeout_s: float) -> dist.Store:
    """The rendezvous store of torchrun's environment (MASTER_ADDR/PORT: the launcher's own store,
    or rank 0's) under a prefix of this attempt (torchrun's TORCHELASTIC_RESTART_COUNT). With
    ``init_method="env://"`` the workers that torchrun restarted after a failure (--max-restarts)
    failed to connect to each other in most tries here (gloo, torch 2.13: "connectFullMesh
    failed ... Connection refused", as in pytorch/pytorch#167288); with a prefix of ours per
    attempt every try connected."""
    agent_store = os.environ.get("TORCHELASTIC_USE_AGENT_STORE") == "True"  # the launcher hosts it
    store = dist.TCPStore(os.environ["MASTER_ADDR"], int(os.environ["MASTER_PORT"]), world,
                          is_master=rank == 0 and not agent_store, timeout=timedelta(seconds=timeout_s))
    return dist.PrefixStore(f"atgs/attempt_{os.environ.get('TORCHELASTIC_RESTART_COUNT', '0')}/", store)


def _wire(t: torch.Tensor) -> torch.Tensor:
    """``t`` as the collectives carry it: contiguous, bool as bytes (gloo sends no bool)."""
    t = t.contiguous()
    return t.view(torch.uint8) if t.dtype == torch.bool else t


SEND_BYTES = 16 * 2**20  # the most one send of the checkpoint's rows carries (rank 0 holds one)


def _runs(rows: int, like: torch.Tensor) -> list[tuple[int, int]]:
    """``rows`` rows shaped as ``like``'s (one row, or none) in runs of at most SEND_BYTES
    (one row at least): what both ends of :meth:`Workers.rows_to_leader` cut a table into."""
    row_bytes = max(1, math.prod(like.shape[1:]) * like.element_size())
    step = max(1, SEND_BYTES // row_bytes)
    return [(a, min(a + step, rows)) for a in range(0, rows, step)]


class Workers:
    """This process among the workers of a run: its rank, the process group and the collectives
    of a step. Every method is collective (all workers call it, in the same order) unless it says
    otherwise."""

    def __init__(self, rank: int, world: int, device: torch.device, backend: str,
                 store: dist.Store | None = None, group: "dist.ProcessGroup | None" = None, nodes: int = 1) -> None:
        self.rank, self.world, self.device, self.backend = rank, world, device, backend
        self.store = store  # the rendezvous store (close() meets the others there after the last collective)
        # None: the whole run; else a subgroup (:meth:`crew`), whose rank and world these are
        self.group = group
        self.run_rank = rank if group is None else dist.get_rank()  # (in messages: the rank torchrun gave)
        self.nodes = nodes  # machines of the run (torchrun's --nnodes: WORLD_SIZE / LOCAL_WORLD_SIZE)
        self.comm = device if backend == "nccl" else torch.device("cpu")  # where collectives run
        self.traffic = Traffic()
        self._written: torch.Tensor | None = None  # per slot: latest view that wrote its last position

    @classmethod
    def from_env(cls, device: torch.device, timeout_s: float) -> "Workers | None":
        """Join the run's process group from torchrun's environment (None for one process).
        ``device``: the kind of device to train on (a CUDA worker takes GPU LOCAL_RANK mod GPUs);
        ``timeout_s``: how long a collective waits for the others before this worker stops."""
        world = int(os.environ.get("WORLD_SIZE", "1"))
        if world <= 1:
            return None
        rank, local_rank = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
        local_world = int(os.environ.get("LOCAL_WORLD_SIZE", str(world)))
        if device.type == "cuda":
            device = torch.device("cuda", local_rank % torch.cuda.device_count())
            torch.cuda.set_device(device)
        backend = _backend(device, local_world)
        store = _attempt_store(rank, world, timeout_s)
        dist.init_process_group(backend, store=store, rank=rank, world_size=world, timeout=timedelta(seconds=timeout_s))
        return cls(rank, world, device, backend, store, nodes=max(1, world // max(1, local_world)))

    def crew(self, size: int) -> "Workers":
        """This worker's crew: the ``size`` consecutive ranks it belongs to (so one node's, as
        torchrun numbers ranks node by node), as a :class:`Workers` of its own whose collectives
        (:meth:`reduce_step`, :meth:`stats_reduced`) run among them only. Collective over the
        whole run: every worker creates every crew's process group, in the same order."""
        if self.group is not None or self.world % size:
            raise AssertionError("crews are cut from the whole run, in equal sizes")
        mine = None
        for first in range(0, self.world, size):
            ranks = list(range(first, first + size))
            group = self._call(dist.new_group, ranks)
            if self.rank in ranks:
                mine = group
        return Workers(self.rank % size, size, self.device, self.backend, group=mine, nodes=self.nodes)

    @property
    def leads(self) -> bool:
        """Rank 0: it prints, evaluates and writes the run's files (not collective)."""
        return self.rank == 0

    def close(self, together: bool = True) -> None:
        """Leave the process group. ``together`` (every worker ending normally): first wait at a
        barrier, then until every worker is past it (counted in the rendezvous store, outside the
        process group), so that no worker tears its connections down while another still waits
        for the barrier's last message (gloo then aborted a process at exit: "terminate called
        without an active exception"; a gloo barrier alone still did, rarely); a failed barrier
        (a worker gone) is no error here. Without ``together`` (leaving on an error) it is not
        collective."""
        if not dist.is_initialized():
            return
        if together:
            try:
                dist.barrier()
                self._all_past_the_barrier()
            except Exception:  # noqa: BLE001 - the others are gone or failing: leave anyway
                pass
        dist.destroy_process_group()

    def _all_past_the_barrier(self, timeout_s: float = 60.0) -> None:
        if self.store is None:
            return
        self.store.add("closing", 1)
        deadline = time.monotonic() + timeout_s
        while self.store.add("closing", 0) < self.world and time.monotonic() < deadline:
            time.sleep(0.005)

    def share(self, n: int) -> range:
        """This worker's views of a step's ``n``: a contiguous block, in rank order (not collective)."""
        return range(n * self.rank // self.world, n * (self.rank + 1) // self.world)

    # --- collectives ------------------------------------------------------------------------------
    def _call(self, collective, *args, **kwargs):
        """A collective; a failed or silent peer becomes :class:`WorkerLost` (one line)."""
        try:
            return collective(*args, **kwargs)
        except RuntimeError as e:  # DistBackendError, gloo's closed connections and timeouts
            raise WorkerLost(f"worker {self.run_rank}: lost the other workers ({_reason(e)}); the last checkpoint "
                             "resumes with --resume") from None

    def replicate(self, tensors: Sequence[torch.Tensor]) -> None:
        """Overwrite ``tensors`` with rank 0's (in place, so caches keyed by tensor versions see
        it): every worker starts from the same model whatever its own set-up's round-off."""
        sizes = torch.tensor([t.numel() for t in tensors] + [-t.numel() for t in tensors], dtype=torch.int64,
                             device=self.comm)
        self._call(dist.all_reduce, sizes, op=dist.ReduceOp.MAX)
        n = len(tensors)
        if bool((sizes[:n] != -sizes[n:]).any()):
            raise WorkerLost(f"worker {self.run_rank}: the workers built models of different sizes from the scene; "
                             "they must see the same --data and flags")
        with torch.no_grad():
            for t in tensors:
                buf = t.detach().to(self.comm, copy=True).contiguous()
                self._call(dist.broadcast, buf, 0)
                t.copy_(buf.to(t.device))

    def gather_to_leader(self, obj) -> list | None:
        """Every worker's ``obj`` (picklable), in rank order, on rank 0; None on the others."""
        out = [None] * self.world if self.leads else None
        self._call(dist.gather_object, obj, out, dst=0)
        return out

    def gather_everywhere(self, obj) -> list:
        """Every worker's ``obj`` (picklable), in rank order, on every worker."""
        out = [None] * self.world
        self._call(dist.all_gather_object, out, obj)
        return out

    def rows_to_leader(self, part: dict[str, torch.Tensor]) -> dict[str, Streamed] | None:
        """Every worker's ``part`` (CPU tensors, the same keys and trailing shapes everywhere),
        concatenated along the first dimension in rank order, for rank 0 to write
        (atgs.io.torch_zip): on rank 0, a :class:`Streamed` per key, whose pieces are its own
        rows and then the others' in runs of at most :data:`SEND_BYTES`, received when the file
        is written; None on the others, which send their part run by run (nothing pickled). So
        no worker holds more than its part and one run (docs/training.md, "Memory per worker").
        Rank 0 must write them in their ``sequence``, the order the others send in
        (atgs.io.torch_zip does)."""
        rows = self.gather_to_leader({k: int(v.shape[0]) for k, v in part.items()})  # a few numbers
        if not self.leads:
            for t in part.values():
                for a, b in _runs(t.shape[0], t[0:1]):
                    self._call(dist.send, _wire(t[a:b]).to(self.comm), dst=0)
            return None

        def pieces(key: str, own: torch.Tensor) -> Iterator[torch.Tensor]:
            yield own
            for rank in range(1, self.world):
                for a, b in _runs(rows[rank][key], own[0:1]):
                    run = torch.empty((b - a, *own.shape[1:]), dtype=own.dtype, device="cpu")
                    wire = _wire(run) if self.comm.type == "cpu" else torch.empty(
                        _wire(run).shape, dtype=_wire(run).dtype, device=self.comm)
                    self._call(dist.recv, wire, src=rank)
                    if wire.device != run.device:
                        _wire(run).copy_(wire.cpu())
                    yield run

        return {key: Streamed((sum(r[key] for r in rows), *t.shape[1:]), t.dtype, partial(pieces, key, t), i)
                for i, (key, t) in enumerate(part.items())}

    def broadcast_floats(self, values: Sequence[float]) -> list[float]:
        """Rank 0's ``values`` on every worker (e.g. its clock, so that all size one schedule)."""
        t = torch.tensor(list(values), dtype=torch.float64, device=self.comm)
        self._call(dist.broadcast, t, 0)
        return [float(x) for x in t.tolist()]

    def reduce_step(self, views: StepViews, dense: Sequence[torch.Tensor], tables: dict[str, torch.Tensor],
                    reach: AnchorReach, stop: bool) -> bool:
        """Put every worker's share of the step into ``views`` (the flags, the losses' totals,
        the sparse gradients merged in rank order), the dense parameters' ``.grad`` (summed) and
        ``reach`` (the largest measured). ``tables``: the model's sparse tables by name (the same
        order on every worker); ``stop``: this worker was asked to stop. Returns whether any was."""
        t0 = time.perf_counter()
        names = list(tables) + [REACH]
        widths = [math.prod(t.shape[1:]) for t in tables.values()] + [1]
        local: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}
        if not views.bad:
            local = {name: merge_rows(parts) for name, parts in views.grads.items()}
        # the reach this worker's decodes measured (recorded even by a non-finite step's)
        ids = (torch.unique(torch.cat(views.decoded)) if views.decoded
               else torch.zeros(0, dtype=torch.int64, device=self.device))
        local[REACH] = (ids, reach.recent.index_select(0, ids)[:, None])
        stop, counts = self._reduce_dense(views, dense, names, local, stop)
        self._gather_sparse(views, names, widths, tables, local, reach, counts)
        self.traffic.steps += 1
        self.traffic.seconds += time.perf_counter() - t0
        self.traffic.tables = sum(t.numel() * t.element_size() for t in tables.values())
        return stop

    def _reduce_dense(self, views: StepViews, dense: Sequence[torch.Tensor], names: list[str],
                      local: dict[str, tuple[torch.Tensor, torch.Tensor]], stop: bool) -> tuple[bool, torch.Tensor]:
        """The step's all-reduce: flags, totals, sparse row counts (each worker in its own slot),
        which dense parameters have a gradient, and those gradients. Returns (stop, every worker's
        row counts: workers x items)."""
        loss = float(torch.stack(views.losses).sum()) if views.losses else 0.0
        psnr = float(torch.stack(views.psnrs).sum()) if views.psnrs else 0.0
        counts = torch.zeros(self.world, len(names), device="cpu")  # host numbers, sent through self.comm
        for i, name in enumerate(names):
            if name in local:
                counts[self.rank, i] = local[name][0].numel()
        header = torch.tensor([float(views.bad), float(stop), loss, psnr, len(views.losses), views.n_gauss],
                              device="cpu")
        has = torch.tensor([float(p.grad is not None) for p in dense], device="cpu")
        grads = [p.grad.detach().reshape(-1) if p.grad is not None else torch.zeros(p.numel(), device=p.device)
                 for p in dense]
        buf = torch.cat([header.to(self.comm), counts.reshape(-1).to(self.comm), has.to(self.comm)]
                        + [g.to(self.comm, torch.float32) for g in grads])
        if not max(float(counts.max()), float(views.n_gauss)) < _EXACT:
            raise RuntimeError("a step's counts exceed what the workers' exchange carries exactly (2^24)")
        self._call(dist.all_reduce, buf, group=self.group)
        self.traffic.dense += buf.numel() * buf.element_size()
        head = buf[:_HEADER].tolist()
        at = _HEADER
        counts = buf[at:at + counts.numel()].reshape(counts.shape).round().long().cpu()
        at += counts.numel()
        has_any = buf[at:at + len(dense)].tolist()
        at += len(dense)
        views.bad = head[0] > 0
        views.totals = (head[2], head[3], int(round(head[4])), int(round(head[5])))
        for p, flag in zip(dense, has_any):
            n = p.numel()
            p.grad = buf[at:at + n].view_as(p).to(p.device, p.dtype) if flag > 0 and not views.bad else None
            at += n
        return head[1] > 0, counts

    def _gather_sparse(self, views: StepViews, names: list[str], widths: list[int],
                       tables: dict[str, torch.Tensor], local: dict[str, tuple[torch.Tensor, torch.Tensor]],
                       reach: AnchorReach, counts: torch.Tensor) -> None:
        """The step's all-gather: per item its rows (int32 carried as float32 bits) and values, in
        the order of ``names``; then every worker merges all of them in rank order."""
        sizes = [int(sum(int(counts[r, i]) * (1 + widths[i]) for i in range(len(names)))) for r in range(self.world)]
        longest = max(sizes)
        pieces = []
        for i, name in enumerate(names):
            if name in local and local[name][0].numel():
                rows, vals = local[name]
                pieces += [rows.to(self.comm, torch.int32).view(torch.float32),
                           vals.detach().reshape(-1).to(self.comm, torch.float32)]
        mine = torch.cat(pieces) if pieces else torch.zeros(0, device=self.comm)
        mine = torch.cat([mine, torch.zeros(longest - mine.numel(), device=self.comm)])
        everyone = [torch.empty(longest, device=self.comm) for _ in range(self.world)]
        self._call(dist.all_gather, everyone, mine, group=self.group)
        self.traffic.sparse += longest * 4
        self.traffic.sparse_rows += int(counts[self.rank, :-1].sum())
        parts: dict[str, list[tuple[torch.Tensor, torch.Tensor]]] = {}
        for r, buf in enumerate(everyone):
            at = 0
            for i, name in enumerate(names):
                n = int(counts[r, i])
                if n == 0:
                    continue
                rows = buf[at:at + n].view(torch.int32).to(self.device, torch.int64)
                at += n
                vals = buf[at:at + n * widths[i]].to(self.device)
                at += n * widths[i]
                shape = (n,) + (tuple(tables[name].shape[1:]) if name != REACH else (1,))
                parts.setdefault(name, []).append((rows, vals.reshape(shape)))
        reached = parts.pop(REACH, [])
        for rows, vals in reached:  # (rows unique within a worker's part)
            reach.recent[rows] = torch.maximum(reach.recent[rows], vals[:, 0].to(reach.recent.dtype))
        views.grads = {} if views.bad else {name: [merge_rows(p)] for name, p in parts.items()}

    # --- densification statistics ------------------------------------------------------------------
    def note_positions(self, stats, slots: torch.Tensor, stamp: int) -> None:
        """Slots whose last position this worker's view ``stamp`` (step * views + view) just wrote
        (not collective)."""
        n = stats.num_slots
        if self._written is None or self._written.numel() != n:
            self._written = torch.full((n,), -1, dtype=torch.int64, device=stats.device)
        self._written.index_fill_(0, slots, stamp)

    @contextmanager
    def stats_reduced(self, stats, anchors: Callable[[], range] | None = None) -> Iterator[None]:
        """While the block runs, ``stats`` (atgs.train.densify.DensifyStats) hold the sums of every
        worker's views and the last positions of the latest views (the same on every worker);
        afterwards rank 0 keeps the sums and the others count their own views from zero.
        ``anchors``: only these anchors' statistics (the time partition's shared anchors, or a
        time group's own ones; the others are left as they are), read before and after the block.
        (The statistics travel as the buffers they flatten themselves into.)"""
        block = range(stats.num_anchors) if anchors is None else anchors()
        n0, n1 = block.start * stats.slots_per_anchor, block.stop * stats.slots_per_anchor
        written = (self._written[n0:n1] if self._written is not None and self._written.numel() == stats.num_slots
                   else torch.full((n1 - n0,), -1, dtype=torch.int64, device=stats.device))
        latest = written.to(self.comm, copy=True)
        self._call(dist.all_reduce, latest, op=dist.ReduceOp.MAX, group=self.group)
        latest = latest.to(stats.device)
        mine = (written == latest) & (latest >= 0)
        last = stats.positions(block)
        ours = torch.where(mine[:, None], last, torch.zeros_like(last))
        buf = torch.cat([stats.flat_sums(block), ours.reshape(-1)]).to(self.comm)
        self._call(dist.all_reduce, buf, group=self.group)
        self.traffic.statistics += buf.numel() * buf.element_size() + latest.numel() * latest.element_size()
        buf = buf.to(stats.device)
        sums = buf.numel() - ours.numel()
        stats.restore_sums(block, buf[:sums])
        stats.set_positions(block, torch.where((latest >= 0)[:, None], buf[sums:].view_as(last), last))
        try:
            yield
        finally:
            self._written = None
            self.own_sums(stats, None if anchors is None else anchors())

    def own_sums(self, stats, anchors: range | None = None) -> None:
        """From here on this worker's statistics sums count its own views only (rank 0's also
        what was summed before): after a reduction, and on a resume (not collective).
        ``anchors``: only these ones' (see :meth:`stats_reduced`)."""
        if self.rank != 0:
            stats.zero_sums(range(stats.num_anchors) if anchors is None else anchors)
