"""Several workers on a CUDA machine: two workers sharing one GPU (gloo through host memory: NCCL
refuses two ranks on one device) against one process on the same GPU, the same global batch and
seed: do their parameters agree, and how fast is a step. It proves the CUDA path of
atgs/train/distributed.py; the speed of a toy scene on the slow dense torch rasterizer (gsplat
needs compiling there) says nothing about scaling.

    python bench/distributed_cuda.py          # writes bench/results/distributed_cuda.json (or --out)
"""

from __future__ import annotations

import json
import os
import socket
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.multiprocessing as mp
import tyro

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))  # the toy scene of the test suite


@dataclass
class Config:
    steps: int = 40
    views: int = 4
    backend: str = "torch"
    """Rasterizer: torch (the dense reference: nothing to compile) or cuda (gsplat)."""
    device: str = "cuda"
    """cpu only to try the script where there is no GPU."""
    out: Path = ROOT / "bench" / "results" / "distributed_cuda.json"


def _trainer(out: Path, cfg: Config, workers=None):
    from _harness import build_trainer
    from builders import make_toy_scene

    scene = make_toy_scene(num_frames=6, num_cameras=4, width=40, height=32, keyframes=3)
    device = workers.device if workers is not None else torch.device(cfg.device)
    return build_trainer(scene, out, "tiny", iterations=cfg.steps, device=str(device), workers=workers,
                         train={"views_per_step": cfg.views, "cameras_per_frame": 2, "render_backend": cfg.backend})


def _timed_run(tr) -> float:
    sync = torch.cuda.synchronize if tr.device.type == "cuda" else (lambda: None)
    sync()
    t0 = time.perf_counter()
    tr.run_steps(progress=False)
    sync()
    return time.perf_counter() - t0


def _worker(rank: int, world: int, port: int, d: str, cfg: Config) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE=str(world),
                      LOCAL_RANK=str(rank), LOCAL_WORLD_SIZE=str(world))
    from atgs.train.distributed import Workers

    workers = Workers.from_env(torch.device(cfg.device), timeout_s=120)
    try:
        tr = _trainer(Path(d) / "two", cfg, workers)
        seconds = _timed_run(tr)
        tr.save(Path(d) / "two.pt")  # collective (the densify statistics are reduced); rank 0 writes
        if rank == 0:
            (Path(d) / "two.json").write_text(json.dumps({"seconds": seconds, "backend": workers.backend,
                                                         "device": str(workers.device)}))
    finally:
        workers.close()


def main(cfg: Config) -> None:
    assert cfg.device == "cpu" or torch.cuda.is_available(), "no CUDA device"
    with tempfile.TemporaryDirectory() as d:
        tr = _trainer(Path(d) / "one", cfg)
        one_s = _timed_run(tr)
        tr.save(Path(d) / "one.pt")
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        mp.spawn(_worker, args=(2, port, d, cfg), nprocs=2, join=True)
        two = json.loads((Path(d) / "two.json").read_text())
        a = torch.load(Path(d) / "one.pt", weights_only=True)["model"]
        b = torch.load(Path(d) / "two.pt", weights_only=True)["model"]
    floats = [k for k in a if torch.is_tensor(a[k]) and a[k].is_floating_point() and a[k].numel()]
    diffs = {k: float((a[k].double() - b[k].double()).abs().max() / a[k].double().abs().max().clamp_min(1e-12))
             for k in floats}
    worst = max(diffs, key=diffs.get)
    result = {"device_name": torch.cuda.get_device_name(0) if cfg.device == "cuda" else "cpu", "torch": torch.__version__, "steps": cfg.steps,
              "views_per_step": cfg.views, "rasterizer": cfg.backend, "two_workers": two,
              "seconds_one_process": round(one_s, 2), "seconds_two_workers": round(two["seconds"], 2),
              "same_tensors": sorted(a) == sorted(b),
              "max_relative_difference": diffs[worst], "worst_tensor": worst,
              "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    cfg.out.parent.mkdir(parents=True, exist_ok=True)
    cfg.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main(tyro.cli(Config))
