"""Scenes shared by the viewer benchmarks (bench/viewer.py, bench/gpu.py): random Gaussians of
a fixed size distribution, the camera that sees them, and untrained ATGS models."""

from __future__ import annotations

import math
import statistics
import time

import numpy as np
import torch

from atgs.cameras import Camera, look_at
from atgs.gaussians import Gaussians


def random_gaussians(n: int, seed: int = 0, device: str | torch.device = "cpu") -> Gaussians:
    """N Gaussians in a 2x2x2 box with a fixed size distribution (independent of N): seen by
    the 1280x720 bench camera a typical splat has sigma ~3 px, i.e. a ~20 px wide 3-sigma quad
    (the SPEC's reference size), so the per-frame work can be compared across N."""
    gen = torch.Generator().manual_seed(seed)
    typical = 0.0125
    g = Gaussians(
        means=torch.rand(n, 3, generator=gen) * 2 - 1,
        quats=torch.randn(n, 4, generator=gen),
        scales=typical * torch.exp(torch.randn(n, 3, generator=gen) * 0.3),
        opacities=torch.rand(n, generator=gen) * 0.8 + 0.1,
        colors=torch.rand(n, 3, generator=gen),
    )
    return g if torch.device(device).type == "cpu" else g.to(device)


def bench_camera(width: int, height: int, angle: float = 0.0) -> Camera:
    """A camera 3.2 units from the box centre with a 50 degree vertical field of view."""
    f = 0.5 * height / math.tan(math.radians(25))
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    eye = np.array([3.2 * math.cos(angle), 3.2 * math.sin(angle), 1.0])
    return Camera("bench", width, height, K, look_at(eye, np.zeros(3), np.array([0, 0, 1.0])))


def untrained_model(preset_name: str = "cpu", num_points: int = 6_000, frames: int = 24):
    """An initialised (untrained) ATGS model of a preset over the points of the synthetic scene
    (4 keyframes); its anchors and Gaussians have the count and sizes an initialised model has."""
    from atgs.model.atgs_model import ATGSModel
    from atgs.train.config import preset
    from atgs.viewer.source import SyntheticSource

    mcfg, _ = preset(preset_name)
    src = SyntheticSource(num_gaussians=num_points, frames=frames)
    pts = src.gaussians_at_frame(0).means
    gen = torch.Generator().manual_seed(0)
    kf = torch.randint(0, 4, (pts.shape[0],), generator=gen)
    scene_kf = [round(j * (frames - 1) / 3) for j in range(4)]
    return ATGSModel.from_points(mcfg, pts, kf, scene_kf, frames, 30.0, src.cameras)


def warm_renderer(gl: str):
    """(context, SplatRenderer) on a headless context, its shaders compiled by a first draw."""
    from atgs.headless_gl import create_headless_context
    from atgs.viewer.packing import pack_gaussians
    from atgs.viewer.splat_renderer import SplatRenderer

    ctx = create_headless_context(gl)
    renderer = SplatRenderer(ctx)
    renderer.set_gaussians(pack_gaussians(random_gaussians(1000)))
    renderer.render(bench_camera(64, 64))
    return ctx, renderer


def time_frames(renderer, g: Gaussians, width: int, height: int, repeats: int) -> dict:
    """Median ms of the stages of a new video frame (pack: tensors -> columns in host memory,
    upload, sort, draw) and of a camera move (sort + draw), over ``repeats`` frames, with the
    FPS they make. The Gaussians stay where they are (CUDA: packed and sorted there)."""
    from atgs.viewer.packing import pack_gaussians
    from atgs.viewer.splat_renderer import RenderSettings

    t = {k: [] for k in ("pack_ms", "upload_ms", "sort_ms", "draw_ms", "move_sort_ms", "move_draw_ms")}
    # one untimed frame first: buffers sized, first-use costs (CUDA's lazily loaded sort
    # kernels) paid; with 2 repeats the median would otherwise be half a first frame
    renderer.set_gaussians(pack_gaussians(g))
    renderer.render(bench_camera(width, height, -0.05), RenderSettings(), sync=True)
    for r in range(repeats):
        if g.means.is_cuda:
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        packed = pack_gaussians(g)
        t["pack_ms"].append((time.perf_counter() - t0) * 1e3)
        t["upload_ms"].append(renderer.set_gaussians(packed))
        renderer.render(bench_camera(width, height, 0.1 * r), RenderSettings(), sync=True)
        t["sort_ms"].append(renderer.timings.sort_ms)
        t["draw_ms"].append(renderer.timings.draw_ms)
        # same Gaussians, moved camera: the sort is redone, nothing else is uploaded
        renderer.render(bench_camera(width, height, 0.1 * r + 0.05), RenderSettings(), sync=True)
        t["move_sort_ms"].append(renderer.timings.sort_ms)
        t["move_draw_ms"].append(renderer.timings.draw_ms)
    m = {k: float(statistics.median(v)) for k, v in t.items()}
    row = {k: m[k] for k in ("pack_ms", "upload_ms", "sort_ms", "draw_ms")}
    row["camera_move_ms"] = m["move_sort_ms"] + m["move_draw_ms"]
    row["fps_new_frame"] = 1000.0 / sum(row[k] for k in ("pack_ms", "upload_ms", "sort_ms", "draw_ms"))
    row["fps_camera_move"] = 1000.0 / row["camera_move_ms"]
    return row
