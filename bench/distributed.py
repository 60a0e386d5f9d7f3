"""Several workers on one machine: steps per second and held-out PSNR at equal wall time, the bytes
the workers exchange per step, and the parts of a step that a scaling model needs.

    python bench/distributed.py                       # the three cases, 3 minutes each, then the anatomy
    python bench/distributed.py --minutes 1 --cases 2x1
    python bench/distributed.py --seeds 0 1 2          # every case once per seed (its spread in the JSON)
    python bench/distributed.py --part memory         # peak memory per worker as frames grow (below)
    python bench/distributed.py --part exchange       # bytes per step of each partition on 4 workers

Cases (one after the other: the machine has 2 cores): "1x2" is one worker with two torch threads,
"2x1" two workers (``atgs-train --workers 2``) with one thread each. Both train preset ``cpu`` on
the built-in scene with two views per step (the global batch both share) for a ``--minutes``
budget, through atgs-train (so its final evaluation, every frame of the held-out camera, scores
them), without the velocities from optical flow (``--flow`` for them: their set-up would take
most of a short budget here). The anatomy times the parts of one worker's step in-process (one thread, the preset's
model at its start): the views (decode, render, backward), the rest (the sparse and dense updates,
densification), and what the exchange of two workers costs. From these and the bytes per step,
:func:`scaling_model` predicts a step on W workers (its assumptions are in the JSON and in
docs/training.md, "Several workers"). Results: bench/results/distributed.json.

The memory part (``--part memory``, its own entry of the JSON): a synthetic capture of 250,
500 and 1,000 frames (4 cameras at 64x48, a keyframe every 10 frames; synthesized and prepared
once into the cache, seconds each) trained for a few steps by N workers of one partition
(torch.multiprocessing, gloo), a model whose per-segment tables dominate (a segment every 10
frames, 8 levels of 2^15 rows), each worker reporting its peak resident memory (VmHWM)
after its set-up, after the steps, and after the checkpoint (rank 0 writes the whole model, each
worker's part received as it writes), and after the final evaluation (every frame, each worker
its own); then the checkpoint resumed by as many fresh workers, each reporting its peak after
``Trainer.resume`` and one step.
Cases "FRAMESxWORKERS[views|time|both]", e.g. 500x2time (both: 2 time groups).

The exchange part (``--part exchange``, its own entry): the built-in scene on 4 workers of one
thread for ``--exchange-steps`` steps (4 processes on 2 cores: their times say nothing, their bytes
do) at one global batch of 4 views, partitioned by views, by time and by both (2 time groups of 2):
the bytes each worker puts into the collectives among all workers and, by both, among its time
group's. From them, :func:`two_node_model` compares the partitions on 2 nodes of 4 GPUs, where
what crosses between the nodes is the cost.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import json
import os
from pathlib import Path
import re
import resource
import socket
import subprocess
import sys
import time
from typing import Literal

import tyro
from _docs import run_stamp  # bench/ (the script's own folder is on sys.path)
from _harness import build_trainer

from atgs.data.scene import PreparedScene
from atgs.data.synth.videos import ensure_default_scene
from atgs.io.cache import cache_dir
from atgs.train.trainer import Trainer

ROOT = Path(__file__).resolve().parent.parent
# name: (workers, torch threads each, partition, views per step of the whole run)
CASES = {"1x2": (1, 2, "views", 2), "2x1": (2, 1, "views", 2), "2x1time": (2, 1, "time", 2),
         "4x1views": (4, 1, "views", 4), "4x1time": (4, 1, "time", 4), "4x1both": (4, 1, "both", 4)}
VIEWS = 2  # views per step of the whole run, the speed cases (the time partition's flag is per worker)
TIME_GROUPS = 2  # of the "both" cases


@dataclass
class Distributed:
    part: Literal["speed", "memory", "exchange"] = "speed"
    cases: tuple[str, ...] = ("1x2", "2x1", "2x1time")
    minutes: float = 3.0
    seeds: tuple[int, ...] = (0,)
    """--train.seed of the runs: each case runs once per seed (cases alternate within a seed, so a
    change of the machine's load reaches every case); "runs" keeps the first seed's."""
    flow: bool = False
    """Velocities from optical flow at the start (a set-up of minutes here, counted in the budget:
    off, so that the budget measures training)."""
    anatomy_steps: int = 30
    memory_cases: tuple[str, ...] = ("250x1time", "500x1time", "500x2time", "500x2views", "1000x2time",
                                     "1000x4time")
    memory_steps: int = 10
    exchange_cases: tuple[str, ...] = ("4x1views", "4x1time", "4x1both")
    exchange_steps: int = 40
    cache: Path = field(default_factory=cache_dir)
    work_dir: Path = Path("/tmp/atgs-bench-distributed")
    out: Path = ROOT / "bench" / "results" / "distributed.json"


def views_flag(workers: int, partition: str, batch: int) -> int:
    """--train.views-per-step for a global batch of ``batch`` views: the time partition's flag is
    per worker, the both partition's per time group."""
    return {"views": batch, "time": batch // workers, "both": batch // TIME_GROUPS}[partition]


def run_case(name: str, args: Distributed, seed: int = 0, steps: int | None = None,
             extra: tuple[str, ...] = ()) -> dict:
    """atgs-train with a budget of ``args.minutes`` (or ``steps`` steps; ``extra`` flags): its
    result.json, wall time and the load."""
    workers, threads, partition, batch = CASES[name]
    views = views_flag(workers, partition, batch)
    out = args.work_dir / name
    length = ["--train.iterations", str(steps)] if steps else ["--train.minutes", str(args.minutes)]
    cmd = [sys.executable, "-m", "atgs.cli.train", "cpu", "--out", str(out), "--overwrite",
           "--train.seed", str(seed), *length, *extra,
           "--train.views-per-step", str(views), "--train.threads", str(threads),
           "--train.partition", partition, "--train.time-groups", str(TIME_GROUPS if partition == "both" else 0),
           "--workers", str(workers), "--no-progress", "--cache-dir", str(args.cache),
           "--train.velocity-from-flow" if args.flow else "--train.no-velocity-from-flow"]
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT,
                          env={**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": str(threads)})
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{name}: atgs-train failed ({proc.returncode}): {proc.stderr.strip()[-400:]}")
    r = json.loads((out / "result.json").read_text())
    return {"workers": workers, "threads": threads, "partition": partition, "seed": seed, "steps": r["steps"],
            "train_seconds": round(r["seconds"], 1), "steps_per_second": round(r["steps"] / r["seconds"], 3),
            "command_seconds": round(wall, 1),
            "anchors": r["anchors"], "psnr": round(r["eval"]["psnr"], 3), "ssim": round(r["eval"]["ssim"], 4),
            "exchange": r.get("workers"), "load_before": round(load, 2), "load_after": round(os.getloadavg()[0], 2)}


def over_seeds(runs: list[dict]) -> dict:
    """A case's runs of several seeds: each one's PSNR and pace, their mean and range."""
    psnr = [r["psnr"] for r in runs]
    pace = [r["steps_per_second"] for r in runs]
    return {"seeds": [r["seed"] for r in runs], "psnr": psnr, "ssim": [r["ssim"] for r in runs],
            "steps_per_second": pace, "steps": [r["steps"] for r in runs],
            "load_before": [r["load_before"] for r in runs],
            "psnr_mean": round(sum(psnr) / len(psnr), 3), "psnr_min": min(psnr), "psnr_max": max(psnr),
            "steps_per_second_mean": round(sum(pace) / len(pace), 3)}


def anatomy(scene, args: Distributed) -> dict:
    """Seconds of one worker's step (one thread, preset cpu at its start): its views and the rest."""
    tr = build_trainer(scene, args.work_dir / "anatomy", "cpu", iterations=5000,
                       train={"views_per_step": VIEWS, "velocity_from_flow": args.flow}, threads=1)
    spent = {"views": 0.0}
    learn = Trainer._learn_view

    def timed(self, *a):
        t0 = time.perf_counter()
        try:
            return learn(self, *a)
        finally:
            spent["views"] += time.perf_counter() - t0

    for _ in range(5):  # caches warm up
        tr.train_step()
    Trainer._learn_view = timed
    try:
        t0 = time.perf_counter()
        for _ in range(args.anatomy_steps):
            tr.train_step()
        total = time.perf_counter() - t0
    finally:
        Trainer._learn_view = learn
    n = args.anatomy_steps
    tables = sum(t.numel() * t.element_size() for t in tr.model.sparse_tensors().values())
    dense = sum(p.numel() * 4 for g in tr.dense_opt.param_groups for p in g["params"])
    return {"steps": n, "anchors": tr.model.num_anchors, "seconds_per_step": total / n,
            "view_seconds": spent["views"] / n / VIEWS, "rest_seconds_per_step": (total - spent["views"]) / n,
            "sparse_table_bytes": tables, "decoder_bytes": dense}


def scaling_model(parts: dict, exchange: dict, workers: int, views_per_worker: int, bandwidth: float,
                  latency: float) -> dict:
    """A step on ``workers`` workers of ``views_per_worker`` views each, from one worker's
    measured parts: every worker renders its views (view_seconds each) and all do the rest
    (rest_seconds: the updates run on every worker); the exchange is a ring all-reduce of the
    dense payload (2 (W-1)/W of it on the wire per worker) and an all-gather of each worker's
    sparse payload ((W-1) payloads received), at ``bandwidth`` bytes/s with ``latency`` seconds
    per ring hop. The sparse payload per worker is the measured one of two views (it grows with
    the views a worker renders, not with W)."""
    w = workers
    dense, sparse = exchange["dense_bytes_per_step"], exchange["sparse_bytes_per_step"] * views_per_worker
    comm = 2 * (w - 1) / w * dense / bandwidth + (w - 1) * sparse / bandwidth + 3 * (w - 1) * latency
    step = parts["rest_seconds_per_step"] + views_per_worker * parts["view_seconds"] + comm
    one = parts["rest_seconds_per_step"] + w * views_per_worker * parts["view_seconds"]
    return {"workers": w, "views_per_step": w * views_per_worker, "step_seconds": step,
            "exchange_seconds": comm, "one_worker_step_seconds": one, "speed_up": one / step,
            "dense_table_all_reduce_seconds": 2 * (w - 1) / w * exchange["dense_tables_bytes_per_step"] / bandwidth}


# --- memory: each worker's peak as the frames grow with the workers ------------------------------------
MEMORY_SYNTH = {"cameras": 4, "width": 64, "height": 48, "texture_size": 128}
FRAMES_PER_KEYFRAME = FRAMES_PER_SEGMENT = 10


def memory_overrides(partition: str, world: int, frames: int) -> tuple[dict, dict]:
    """(model, train) overrides of the tiny preset: per-segment tables that dominate the model
    (about 2 MB of table and 6 MB with its optimizer state per segment), a keyframe every 10
    frames (the synthetic capture's moving points would make one of most frames) of at most 300
    anchors; a view per worker and step (by both: a time group's views shared by its workers)."""
    model = {"num_keyframes": frames // FRAMES_PER_KEYFRAME, "max_anchors_per_keyframe": 300,
             "frames_per_segment": FRAMES_PER_SEGMENT, "hash": {"levels": 8, "log2_table_size": 15}}
    train = {"views_per_step": views_flag(world, partition, world), "partition": partition,
             "time_groups": TIME_GROUPS if partition == "both" else 0,
             "velocity_from_flow": False, "camera_exposure": "off"}
    return model, train


def _peak_mb() -> float:
    """This process's peak resident memory (VmHWM). Not ru_maxrss: Linux carries that across the
    exec of a spawned worker, so every worker read at least its launcher's peak (up to 990 MB here)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024  # kB
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _resident_mb() -> float:
    return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _join(rank: int, world: int, port: int):
    """This spawned worker's place among ``world`` (gloo on the CPU, one thread); None alone."""
    from atgs.train.distributed import Workers

    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE=str(world),
                      LOCAL_RANK=str(rank), LOCAL_WORLD_SIZE=str(world), OMP_NUM_THREADS="1")
    import torch

    return Workers.from_env(torch.device("cpu"), timeout_s=600) if world > 1 else None


def memory_worker(rank: int, world: int, port: int, scene_dir: str, out: str, partition: str, steps: int) -> None:
    """One worker of a memory case: its peaks (MB) after the set-up, the steps and the checkpoint."""
    workers = _join(rank, world, port)
    try:
        peaks = {"start": _peak_mb()}
        scene = PreparedScene.load(scene_dir)
        model, train = memory_overrides(partition, world, scene.num_frames)
        tr = build_trainer(scene, Path(out), "tiny", iterations=steps, model=model, train=train, workers=workers)
        peaks["set_up"] = _peak_mb()
        t0 = time.perf_counter()
        for _ in range(steps):
            tr.train_step()
        seconds = time.perf_counter() - t0
        peaks["steps"] = _peak_mb()
        resident = _resident_mb()  # now: what training holds, without the set-up's passing peak
        tr.save(Path(out) / "ckpt.pt")
        peaks["checkpoint"] = _peak_mb()
        t1 = time.perf_counter()
        final = tr.final_evaluation(None)  # every frame of the held-out camera, spread over the workers
        peaks["final_evaluation"] = _peak_mb()
        final_seconds = time.perf_counter() - t1
        tables = {n: t.numel() * t.element_size() for n, t in tr.model.sparse_tensors().items()}
        Path(out, f"memory{rank}.json").write_text(json.dumps({
            "rank": rank, "peak_mb": {k: round(v, 1) for k, v in peaks.items()},
            "resident_mb_after_steps": round(resident, 1), "anchors": tr.model.num_anchors,
            "segments_held": tr.model.hash.num_grids, "table_mb": round(sum(tables.values()) / 2**20, 1),
            "seconds_per_step": round(seconds / steps, 3), "final_evaluation_seconds": round(final_seconds, 1),
            "final_evaluation_views": None if final is None else final["views"],
            "exchange": None if workers is None else workers.traffic.summary(world)}))
    finally:
        if workers is not None:
            workers.close()


def memory_resume_worker(rank: int, world: int, port: int, scene_dir: str, out: str, partition: str) -> None:
    """One worker resuming a memory case's checkpoint (a fresh process, as after a restart): its
    peaks (MB) after ``Trainer.resume`` and after one step."""
    from atgs.train.trainer import Trainer

    workers = _join(rank, world, port)
    try:
        peaks = {"start": _peak_mb()}
        scene = PreparedScene.load(scene_dir)
        tr = Trainer.resume(scene, Path(out) / "ckpt.pt", Path(out) / "resumed", workers=workers,
                            partition=partition)
        peaks["resumed"] = _peak_mb()
        tr.train_step()
        peaks["step"] = _peak_mb()
        Path(out, f"resume{rank}.json").write_text(json.dumps({k: round(v, 1) for k, v in peaks.items()}))
    finally:
        if workers is not None:
            workers.close()


def _spawn_workers(fn, world: int, args: tuple) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    import torch.multiprocessing as mp

    mp.start_processes(fn, args=(world, port, *args), nprocs=world, start_method="spawn")


def memory_case(name: str, args: Distributed) -> dict:
    from atgs.data.synth.scene import SynthConfig

    frames, world, partition = re.fullmatch(r"(\d+)x(\d+)(views|time|both)", name).groups()
    frames, world = int(frames), int(world)
    t0 = time.perf_counter()
    scene_dir = ensure_default_scene(args.cache, SynthConfig(frames=frames, **MEMORY_SYNTH),
                                     keyframes=frames // FRAMES_PER_KEYFRAME, progress=False)
    synth = time.perf_counter() - t0
    out = args.work_dir / f"memory-{name}"
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    os.environ["PYTHONPATH"] = str(ROOT)  # the workers import this checkout's atgs
    _spawn_workers(memory_worker, world, (str(scene_dir), str(out), partition, args.memory_steps))
    workers = [json.loads((out / f"memory{r}.json").read_text()) for r in range(world)]
    _spawn_workers(memory_resume_worker, world, (str(scene_dir), str(out), partition))  # its checkpoint resumed
    for r, w in enumerate(workers):
        w["resume_peak_mb"] = json.loads((out / f"resume{r}.json").read_text())
    return {"frames": frames, "workers": world, "partition": partition, "steps": args.memory_steps,
            "scene_seconds": round(synth, 1), "run_seconds": round(time.perf_counter() - t0, 1),
            "per_worker": workers,
            "largest_peak_mb_before_checkpoint": max(w["peak_mb"]["steps"] for w in workers),
            "largest_resident_mb_after_steps": max(w["resident_mb_after_steps"] for w in workers),
            "largest_peak_mb_of_a_worker_not_writing": max((w["peak_mb"]["checkpoint"] for w in workers[1:]),
                                                           default=None),
            "largest_peak_mb_resuming": max(w["resume_peak_mb"]["resumed"] for w in workers)}


def memory(args: Distributed) -> None:
    results = json.loads(args.out.read_text()) if args.out.is_file() else {}
    part = results.setdefault("memory", {})
    part["stamp"] = run_stamp()
    part["synthetic_capture"] = {**MEMORY_SYNTH, "frames_per_keyframe": FRAMES_PER_KEYFRAME}
    part["model"] = {"preset": "tiny", "frames_per_segment": FRAMES_PER_SEGMENT, "hash_levels": 8,
                     "log2_table_size": 15, "frames_per_keyframe": FRAMES_PER_KEYFRAME,
                     "max_anchors_per_keyframe": 300}
    cases = part.setdefault("cases", {})
    for name in args.memory_cases:
        cases[name] = {**memory_case(name, args), "stamp": run_stamp()}
        print(name, json.dumps(cases[name]), flush=True)
        args.out.write_text(json.dumps(results, indent=1) + "\n")


# --- exchange: what each partition sends, and between which workers -------------------------------------
EXCHANGE_MODEL = ("--model.num-segments", "4")  # every case's model: a segment per worker of the time partition
INTER_NODE = 50e9  # bytes/s per GPU between nodes: a 400 Gb/s InfiniBand NIC per GPU (assumed)
INTRA_NODE = 100e9  # bytes/s per GPU within a node: NVLink, as NCCL's rings reach it (assumed)


def two_node_model(cases: dict, gpus_per_node: int = 4, latency: float = 20e-6) -> dict:
    """Seconds of a step's exchange on 2 nodes of ``gpus_per_node`` GPUs, one view per GPU, from the
    measured payloads per worker and view (4 workers, one view each). Hierarchical collectives:
    what a node's workers put in crosses to the other node once (``gpus_per_node`` payloads over
    the node's ``gpus_per_node`` NICs), then spreads within the node over NVLink. views: every
    worker's touched rows reach every worker (across and within); time: only the shared rows do,
    across and within; both (a time group per node): the shared rows across and within, the owned
    rows within the node only (the crew's all-gather). The dense all-reduce is the same for all
    (and small). Not modelled: a step's compute (the same per view in all three), the batch each
    partition trains with (time: views spread over time within each worker's frames only)."""
    n = gpus_per_node
    w = 2 * n

    def gather(payload: float, crossing: bool, within: int) -> float:
        across = payload * n / (n * INTER_NODE) if crossing else 0.0  # each node's n payloads, n NICs
        spread = (within - 1) * payload / INTRA_NODE  # the all-gather's payloads within the node
        return across + spread + 3 * latency

    views = cases["4x1views"]["exchange"]
    time_ = cases["4x1time"]["exchange"]
    both = cases["4x1both"]["exchange"]
    dense = views["dense_bytes_per_step"]
    allreduce = 2 * (w - 1) / w * dense / INTER_NODE
    out = {
        "views": gather(views["sparse_bytes_per_step"], True, w) + allreduce,
        "time": gather(time_["sparse_bytes_per_step"], True, w) + allreduce,
        "both": (gather(both["sparse_bytes_per_step"], True, w)
                 + gather(both["time_group"]["sparse_bytes_per_step"], False, n) + allreduce),
    }
    crossing = {"views": views["sparse_bytes_per_step"] * n, "time": time_["sparse_bytes_per_step"] * n,
                "both": both["sparse_bytes_per_step"] * n}
    return {"gpus": w, "nodes": 2, "exchange_seconds": out, "bytes_crossing_per_node_per_step": crossing,
            "assumptions": {"inter_node_bytes_per_second_per_gpu": INTER_NODE,
                            "intra_node_bytes_per_second_per_gpu": INTRA_NODE, "latency_seconds_per_hop": latency,
                            "payloads": "measured on 4 CPU workers of one view each (per worker), "
                                        "taken as the 8 GPUs' (the model's size and the views' reach are the same)"}}


def exchange_part(args: Distributed) -> None:
    results = json.loads(args.out.read_text()) if args.out.is_file() else {}
    part = results.setdefault("exchange", {})
    part["stamp"] = run_stamp()
    part["steps"], part["views_per_step"], part["time_groups"] = args.exchange_steps, 4, TIME_GROUPS
    part["model_flags"] = list(EXCHANGE_MODEL)
    cases = part.setdefault("cases", {})
    for name in args.exchange_cases:
        cases[name] = run_case(name, args, steps=args.exchange_steps, extra=EXCHANGE_MODEL)
        print(name, json.dumps(cases[name]), flush=True)
        args.out.write_text(json.dumps(results, indent=1) + "\n")
    if all(name in cases for name in ("4x1views", "4x1time", "4x1both")):
        part["two_nodes"] = two_node_model(cases)
        print("two nodes", json.dumps(part["two_nodes"]), flush=True)
    args.out.write_text(json.dumps(results, indent=1) + "\n")


def main(args: Distributed) -> None:
    if args.part == "memory":
        memory(args)
        return
    if args.part == "exchange":
        exchange_part(args)
        return
    scene = PreparedScene.load(ensure_default_scene(args.cache, progress=False))
    results = json.loads(args.out.read_text()) if args.out.is_file() else {}
    results["stamp"] = run_stamp()
    results["views_per_step"] = VIEWS
    results["minutes"] = args.minutes
    results["velocity_from_flow"] = args.flow
    runs = results.setdefault("runs", {})
    by_seed: dict[str, list[dict]] = {name: [] for name in args.cases}
    for seed in args.seeds:
        for name in args.cases:
            by_seed[name].append(run_case(name, args, seed))
            print(name, seed, by_seed[name][-1], flush=True)
    for name, done in by_seed.items():
        runs[name] = done[0]
    if len(args.seeds) > 1:
        results["over_seeds"] = {name: over_seeds(done) for name, done in by_seed.items()}
    results["anatomy"] = parts = anatomy(scene, args)
    print("anatomy", parts, flush=True)
    exchange = (runs.get("2x1") or {}).get("exchange")
    if exchange:
        # this CPU machine (gloo on the loopback: the measured exchange seconds are what counts),
        # and an 8-GPU node of NVLink: ~100 GB/s per direction reached by NCCL's ring, 20 us a hop,
        # the step's parts scaled by the measured GPU step (docs/gpu.md: 29 ms a step of one view)
        gpu_scale = 0.029 / (parts["rest_seconds_per_step"] + parts["view_seconds"])
        gpu_parts = {k: parts[k] * gpu_scale for k in ("rest_seconds_per_step", "view_seconds")}
        results["scaling"] = {
            "assumptions": {
                "gpu_step_seconds_one_view": 0.029, "gpu_parts": "the CPU's split of a step, scaled to 29 ms",
                "bandwidth_bytes_per_second": 100e9, "latency_seconds_per_hop": 20e-6,
                "views_per_worker": 1, "sparse_bytes": "the 2x1 run's per worker per view, not growing with W"},
            "gpu_8": scaling_model(gpu_parts, exchange, 8, 1, 100e9, 20e-6),
            "gpu_2": scaling_model(gpu_parts, exchange, 2, 1, 100e9, 20e-6),
            "gpu_4": scaling_model(gpu_parts, exchange, 4, 1, 100e9, 20e-6),
        }
        print("scaling", results["scaling"], flush=True)
    args.out.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main(tyro.cli(Distributed))
