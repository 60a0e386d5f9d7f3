"""GL depth sort benchmark: ``GLDepthSort.sort`` + ``ctx.finish()`` (compute shaders,
atgs/viewer/gl_sort.py) against torch's ``back_to_front`` on the CPU, on the same inputs.

    python bench/gl_sort.py          # writes bench/results/gl_sort.json

N random Gaussians (bench/_viewer_scenes.py's box, 100k and 1M) seen by the 1920x1080 bench
camera, with the frustum cull and the 1/255 alpha cutoff, both sorts fed the same quantized
opacity. Each repeat times torch, then the GL sort at every block size, so that all see about
the same load; medians after the warm-up runs (the first llvmpipe runs fault in their buffers).
On llvmpipe (Mesa's CPU rasterizer) the GL sort is expected to lose to torch's CPU radix
sort: it is meant for GPUs, where the Gaussians will be decoded into GL buffers.
"""

from __future__ import annotations

import json
import os
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro

from atgs.headless_gl import create_headless_context, gl_description
from atgs.viewer.gl_sort import BLOCK_SIZE, GLDepthSort
from atgs.viewer.packing import pack_gaussians
from atgs.viewer.sorting import FrustumCull, back_to_front
from atgs.viewer.splat_renderer import ALPHA_MIN, DILATION, NEAR, RADIUS_SIGMAS, clamp_limits
from _docs import run_stamp, write_json_atomic  # bench/_docs.py (the script's own folder is on sys.path)
from _viewer_scenes import bench_camera, random_gaussians


@dataclass
class BenchConfig:
    counts: tuple[int, ...] = (100_000, 1_000_000)
    size: tuple[int, int] = (1920, 1080)
    block_sizes: tuple[int, ...] = (128, 256, 512, 1024, 2048)
    """Radix block sizes of the GL sort to time (the default, BLOCK_SIZE, is marked in the rows)."""
    warmup: int = 4
    repeats: int = 9
    gl: str = "auto"
    out: Path = Path("bench/results/gl_sort.json")


def _median_ms(ts: list[float]) -> float:
    return round(1e3 * statistics.median(ts), 2)


def bench_count(ctx, sorters: dict[int, GLDepthSort], n: int, cfg: BenchConfig) -> dict:
    W, H = cfg.size
    cam = bench_camera(W, H, 0.3)
    cull = FrustumCull(cam.K, W, H, clamp_limits(cam.K, W, H), sigmas=RADIUS_SIGMAS, dilation=DILATION)
    packed = pack_gaussians(random_gaussians(n))
    means, _, scales, opacity_rgb = packed.columns
    opacity = torch.from_numpy(opacity_rgb[:, 0].astype(np.float32) / np.float32(65535))  # what the GL reads
    buffers = [ctx.buffer(np.ascontiguousarray(c).tobytes()) for c in (means, scales, opacity_rgb)]

    def torch_sort() -> torch.Tensor:
        return back_to_front(packed.means, cam.w2c, NEAR, extent=packed.extent, cull=cull, opacity=opacity,
                             min_alpha=ALPHA_MIN)

    def gl_sort(sorter: GLDepthSort):
        order = sorter.sort(*buffers, n, cam.w2c, NEAR, cull, ALPHA_MIN)
        ctx.finish()
        return order

    times: dict[str, list[float]] = {"torch": [], **{f"gl_{b}": [] for b in sorters}}
    load_before = os.getloadavg()
    for rep in range(cfg.warmup + cfg.repeats):
        t0 = time.perf_counter()
        expect = torch_sort()
        if rep >= cfg.warmup:
            times["torch"].append(time.perf_counter() - t0)
        for b, sorter in sorters.items():
            t0 = time.perf_counter()
            order = gl_sort(sorter)
            if rep >= cfg.warmup:
                times[f"gl_{b}"].append(time.perf_counter() - t0)
    drawn = order.drawn()
    if drawn != len(expect):
        raise RuntimeError(f"{n} Gaussians: the GL sort drew {drawn}, torch {len(expect)}")
    got, expect = order.indices(), expect.numpy()
    same_set = bool(np.array_equal(np.sort(got), np.sort(expect)))
    # a key one level off (float32 key scale) moves its Gaussian past its neighbours of that level
    differ = int((got != expect).sum())
    for buf in buffers:
        buf.release()
    return {
        "gaussians": n, "size": f"{W}x{H}", "drawn": drawn, "same_visible_set": same_set,
        "positions_differing_from_torch": differ,
        "torch_ms": _median_ms(times["torch"]), "torch_threads": 1,  # back_to_front sorts with 1 thread on the CPU
        "gl_ms": _median_ms(times[f"gl_{BLOCK_SIZE}"]) if BLOCK_SIZE in sorters else None,
        "gl_ms_by_block_size": {str(b): _median_ms(times[f"gl_{b}"]) for b in sorters},
        "repeats": cfg.repeats, "warmup": cfg.warmup, "loadavg_before": list(load_before),
        "loadavg_after": list(os.getloadavg()),
    }


def main(cfg: BenchConfig) -> None:
    ctx = create_headless_context(cfg.gl)
    sorters = {b: GLDepthSort(ctx, block_size=b) for b in cfg.block_sizes}
    rows = []
    for n in cfg.counts:
        row = bench_count(ctx, sorters, n, cfg)
        print(json.dumps(row), flush=True)
        rows.append(row)
    result = {"gl_renderer": gl_description(ctx), "default_block_size": BLOCK_SIZE, "cpu_count": os.cpu_count(),
              "lp_num_threads": os.environ.get("LP_NUM_THREADS"),  # llvmpipe's threads (unset: one per core)
              "rows": rows, **run_stamp()}
    write_json_atomic(cfg.out, result)
    print(f"wrote {cfg.out}")


if __name__ == "__main__":
    main(tyro.cli(BenchConfig))
