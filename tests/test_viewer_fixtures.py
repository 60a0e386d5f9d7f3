"""A tiny untrained ATGS checkpoint built from the model package's API (no training)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from atgs.cameras import Camera, look_at


def osmesa_renderer():
    """A SplatRenderer on its own OSMesa context, released afterwards (``yield from`` it in a
    module-scoped fixture)."""
    from atgs.headless_gl import create_headless_context
    from viewer.splat_renderer import SplatRenderer

    ctx = create_headless_context("osmesa")
    r = SplatRenderer(ctx)
    yield r
    r.release()
    ctx.release()


def tiny_cameras(n: int = 3, size: tuple[int, int] = (96, 72)) -> list[Camera]:
    W, H = size
    K = np.array([[80.0, 0, W / 2], [0, 80.0, H / 2], [0, 0, 1]])
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = np.array([3.0 * np.cos(a), 3.0 * np.sin(a), 1.0])
        cams.append(Camera(f"cam{i:02d}", W, H, K, look_at(eye, np.zeros(3), np.array([0, 0, 1.0]))))
    return cams


def write_tiny_checkpoint(path: Path, num_frames: int = 9, points: int = 300) -> Path:
    from atgs.checkpoint import save_checkpoint
    from atgs.model.atgs_model import ATGSModel
    from atgs.model.config import HashGridConfig, ModelConfig, to_dict

    cfg = ModelConfig(
        feature_dim=8, gaussians_per_anchor=2, num_keyframes=3, window=3, num_segments=2,
        hash=HashGridConfig(levels=2, features_per_level=2, log2_table_size=8, base_resolution=4, mlp_hidden=8),
        spatial_resolution=4, hidden_opacity=8, hidden_cov=8, hidden_color=8, hidden_offset=8,
        frustum_cull=False,
    )  # fmt: skip
    gen = torch.Generator().manual_seed(0)
    pts = torch.rand(points, 3, generator=gen) * 1.6 - 0.8
    kf = torch.randint(0, 3, (points,), generator=gen)
    cams = tiny_cameras()
    scene_kf = [0, (num_frames - 1) // 2, num_frames - 1]
    model = ATGSModel.from_points(cfg, pts, kf, scene_kf, num_frames, 10.0, cams)
    payload = {
        "model_config": to_dict(cfg), "cameras": [c.to_dict() for c in cams], "test_cameras": [],
        "num_frames": num_frames, "fps": 10.0, "time_range": [0.0, (num_frames - 1) / 10.0],
        "keyframes": model.timeline.keyframe_frames(), "step": 0, "model": model.state_dict(),
    }  # fmt: skip
    save_checkpoint(path, payload)
    return path
