"""Test scaffolding: tiny cameras, tiny models through the package API, a tiny checkpoint, and an
in-memory dynamic toy scene. Imported by the test files (``from builders import ...``); nothing
here ships with the package."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from atgs.cameras import Camera, look_at
from atgs.data.scene import MemoryScene
from atgs.model.atgs_model import ATGSModel
from atgs.model.config import HashGridConfig, ModelConfig
from atgs.render import rasterize_gaussians
from atgs.gaussians import Gaussians
from atgs.timeline import evenly_spaced

UP_Z = np.array([0.0, 0.0, 1.0])


# --- cameras -------------------------------------------------------------------------------------

def textured_copy(scene: MemoryScene, seed: int = 0) -> MemoryScene:
    """``scene`` with noise images everywhere (no uniform backdrop): the mean colour and the
    background by direction then come from textured images."""
    rng = np.random.default_rng(seed)
    h, w = scene.cameras[0].height, scene.cameras[0].width
    frames = {(c, f): rng.integers(40, 256, (h, w, 3), dtype=np.uint8)
              for c in range(len(scene.cameras)) for f in range(scene.num_frames)}
    return MemoryScene(scene.cameras, scene.num_frames, scene.fps, scene.keyframes, scene.points,
                       scene.point_keyframes, scene.test_cameras, frames)


def ring_cameras(n: int = 3, size: tuple[int, int] = (32, 24), focal: float | None = None,
                 radius: float = 3.0, height: float = 1.0) -> list[Camera]:
    """``n`` cameras on a ring around the origin, looking at it (z up); focal 0.9 W by default."""
    W, H = size
    f = 0.9 * W if focal is None else focal
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = np.array([radius * np.cos(a), radius * np.sin(a), height])
        cams.append(Camera(f"cam{i:02d}", W, H, K, look_at(eye, np.zeros(3), UP_Z)))
    return cams


def side_camera(eye=(0.5, -3.0, 0.5), target=(0.5, 0.5, 0.5)) -> Camera:
    """One 32x24 camera (focal 30) looking at the unit cube from the side."""
    return Camera("c", 32, 24, np.array([[30, 0, 16], [0, 30, 12], [0, 0, 1.0]]),
                  look_at(np.array(eye, dtype=np.float64), np.array(target, dtype=np.float64)))


# --- models --------------------------------------------------------------------------------------

def tiny_config(K: int = 3, W: int = 3, M: int = 2, hidden: int = 16, **overrides) -> ModelConfig:
    """The smallest model configuration with every part present (2 hash levels, 4^3 grid)."""
    cfg = ModelConfig(
        feature_dim=8, gaussians_per_anchor=2, num_keyframes=K, window=W, num_segments=M,
        hash=HashGridConfig(levels=2, features_per_level=2, log2_table_size=8, base_resolution=4, mlp_hidden=8),
        spatial_resolution=4, hidden_opacity=hidden, hidden_cov=hidden, hidden_color=hidden, hidden_offset=hidden,
    )  # fmt: skip
    for k, v in overrides.items():
        setattr(cfg, k, v)
    return cfg


def random_point_model(cfg: ModelConfig, F: int, n: int, cameras: list[Camera], fps: float = 10.0,
                       seed: int = 0, randomize: bool = False) -> ATGSModel:
    """A model over ``n`` random points in [-0.8, 0.8]^3 spread over the scene keyframes
    ``evenly_spaced(F, cfg.num_keyframes)``. ``randomize`` fills features and grids with
    non-trivial values (an untrained model has zero features, which hides most numerical problems)."""
    K = cfg.num_keyframes
    gen = torch.Generator().manual_seed(seed)
    pts = torch.rand(n, 3, generator=gen) * 1.6 - 0.8
    kf = torch.randint(0, K, (n,), generator=gen)
    model = ATGSModel.from_points(cfg, pts, kf, evenly_spaced(F, K), F, fps, cameras, seed=seed)
    if randomize:
        randomize_features(model, gen, grid_scale=0.5)
    return model


def keyframe_point_model(cfg: ModelConfig, F: int, K: int, per_keyframe: int, gen: torch.Generator,
                         camera: Camera | None = None) -> ATGSModel:
    """A model over ``per_keyframe`` random points in the unit cube at each of K scene keyframes,
    seen by :func:`side_camera` at 25 fps."""
    pts = torch.rand(per_keyframe * K, 3, generator=gen)
    pk = torch.arange(K).repeat_interleave(per_keyframe)
    return ATGSModel.from_points(cfg, pts, pk, evenly_spaced(F, K), F, 25.0, [camera or side_camera()], seed=0)


def randomize_features(model: ATGSModel, gen: torch.Generator, grid_scale: float = 1.0) -> None:
    """Trained-looking parameters: nonzero anchor features, F_s and hash values."""
    model.anchor_feature = torch.randn(model.anchor_feature.shape, generator=gen)
    model.spatial.table = grid_scale * torch.randn(model.spatial.table.shape, generator=gen)
    model.hash.table = grid_scale * torch.randn(model.hash.table.shape, generator=gen)


def growing_tiny_config(iterations: int):
    """(model, train) configs of the ``tiny`` preset with densification early and eager (anchors
    grow within a few steps) and two views per step (the path that merges sparse gradients)."""
    from atgs.train.config import preset

    m, t = preset("tiny")
    t.iterations = iterations
    t.densify.start, t.densify.interval, t.densify.grad_threshold = 4, 2, 1e-6
    t.densify.success_threshold, t.densify.init_factor, t.densify.min_opacity = 0.1, 1, 1.5
    t.views_per_step = 2
    return m, t


def write_tiny_checkpoint(path: Path, num_frames: int = 9, points: int = 300) -> Path:
    """An untrained 3-camera (96x72) checkpoint of :func:`tiny_config`, without optimizer state."""
    from atgs.checkpoint import save_checkpoint
    from atgs.config_dict import to_dict

    cfg = tiny_config(K=3, W=3, M=2, hidden=8, frustum_cull=False)
    cams = ring_cameras(3, (96, 72), focal=80.0)
    model = random_point_model(cfg, num_frames, points, cams)
    payload = {
        "model_config": to_dict(cfg), "cameras": [c.to_dict() for c in cams], "test_cameras": [],
        "num_frames": num_frames, "fps": 10.0, "time_range": [0.0, (num_frames - 1) / 10.0],
        "keyframes": model.timeline.keyframe_frames(), "step": 0, "model": model.state_dict(),
    }  # fmt: skip
    save_checkpoint(path, payload)
    return path


def train_tiny_checkpoint(out_dir: Path, iterations: int = 30, size: tuple[int, int] = (48, 36)) -> Path:
    """``ckpt.pt`` of the ``tiny`` preset trained ``iterations`` steps on :func:`make_toy_scene`
    (6 frames, 4 cameras of ``size``; ~5 s on 2 cores)."""
    from atgs.train.config import preset
    from atgs.train.trainer import Trainer

    scene = make_toy_scene(num_frames=6, num_cameras=4, width=size[0], height=size[1], keyframes=3)
    m, t = preset("tiny")
    t.iterations = iterations
    Trainer(scene, m, t, out_dir).train(progress=False, final_renders=False)
    return Path(out_dir) / "ckpt.pt"


# --- an in-memory dynamic scene ----------------------------------------------------------------

def make_toy_scene(num_frames: int = 6, num_cameras: int = 5, width: int = 40, height: int = 32,
                   keyframes: int = 3, seed: int = 0) -> MemoryScene:
    """A few coloured static Gaussians and a blob that moves, seen by cameras on a ring (the last
    one held out). Ground truth is rendered with the rasterizer itself, so a model can fit it
    exactly in principle."""
    gen = torch.Generator().manual_seed(seed)
    n_static = 24
    static = (torch.rand(n_static, 3, generator=gen) - 0.5) * torch.tensor([1.6, 1.6, 0.4])
    static_col = torch.rand(n_static, 3, generator=gen) * 0.8 + 0.1
    cams = []
    for i in range(num_cameras):
        a = 2 * np.pi * i / num_cameras
        eye = np.array([3.0 * np.cos(a), 3.0 * np.sin(a), 1.2])
        f = 0.9 * width
        K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])
        cams.append(Camera(f"cam{i:02d}", width, height, K, look_at(eye, np.zeros(3))))

    def blob(frame: int) -> torch.Tensor:
        s = frame / max(1, num_frames - 1)
        return torch.tensor([[-0.6 + 1.2 * s, 0.0, 0.3]])

    frames = {}
    for fr in range(num_frames):
        means = torch.cat([static, blob(fr)])
        n = means.shape[0]
        g = Gaussians(means=means, quats=torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4).contiguous(),
                      scales=torch.cat([torch.full((n_static, 3), 0.12), torch.full((1, 3), 0.2)]),
                      opacities=torch.full((n,), 0.9), colors=torch.cat([static_col, torch.tensor([[1.0, 0.2, 0.1]])]))
        for ci, c in enumerate(cams):
            out = rasterize_gaussians(g, c, backend="auto")
            frames[(ci, fr)] = (out.image.clamp(0, 1) * 255).round().byte().numpy()
    kf_frames = evenly_spaced(num_frames, keyframes)
    # every keyframe re-observes the static points (with triangulation noise), as real captures do
    pts, pk = [], []
    for j in range(len(kf_frames)):
        pts.append(static + 0.02 * torch.randn(n_static, 3, generator=gen))
        pk.append(torch.full((n_static,), j, dtype=torch.int64))
    for j, fr in enumerate(kf_frames):
        pts.append(blob(fr) + 0.08 * torch.randn(4, 3, generator=gen))
        pk.append(torch.full((4,), j, dtype=torch.int64))
    return MemoryScene(cams, num_frames, 30.0, kf_frames, torch.cat(pts).numpy(), torch.cat(pk).numpy(),
                       [cams[-1].name], frames)


# --- a model for decode tests ----------------------------------------------------------------------

DECODE_FRAMES, DECODE_KEYFRAMES = 17, 5
DECODE_CASES = {
    "plain": dict(temporal_fade=False, anchor_velocity=False, opacity_threshold=0.0, camera_clearance=0.0),
    "motion": dict(temporal_fade=True, anchor_velocity=True, opacity_threshold=0.0, camera_clearance=0.0),
    "everything": dict(temporal_fade=True, anchor_velocity=True, smoothing_3d=0.2, camera_clearance=0.25),
    "per-keyframe": dict(anchor_layout="per-keyframe", static_keyframe0=True, temporal_fade=True,
                         anchor_velocity=True, smoothing_3d=0.2),
}


def decode_case_model(case: str) -> ATGSModel:
    """A tiny model with every step of the decode at work (``DECODE_CASES``: which steps are on):
    dense and hashed hash levels, 3 segments, anchors outside the grid box, a camera inside the
    cloud for the clearance; "everything" puts the opacity cut in a wide gap between opacities."""
    from atgs.train.config import preset
    from decode_reference import reference_frame

    F, K = DECODE_FRAMES, DECODE_KEYFRAMES
    cfg, _ = preset("tiny")
    cfg.window, cfg.num_segments, cfg.frustum_cull = 3, 3, True
    # base 2, growth 2: level 0 fits the 2^8 table (dense), levels 1-3 are hashed
    cfg.hash = HashGridConfig(levels=4, features_per_level=2, log2_table_size=8, base_resolution=2,
                              growth=2.0, max_time_resolution=5, mlp_hidden=16)
    for k, v in DECODE_CASES[case].items():
        setattr(cfg, k, v)
    gen = torch.Generator().manual_seed(1)
    pts = torch.rand(30 * K, 3, generator=gen)
    # a second camera inside the cloud: the clearance cuts Gaussians around it
    inner = Camera("inner", 32, 24, np.array([[30, 0, 16], [0, 30, 12], [0, 0, 1.0]]),
                   look_at(np.array([0.5, 0.5, 0.5]), np.array([2.0, 0.5, 0.5])))
    model = ATGSModel.from_points(cfg, pts, torch.arange(K).repeat_interleave(30), evenly_spaced(F, K), F, 25.0,
                                  [side_camera(), inner], seed=0)
    randomize_features(model, gen)
    model.anchor_log_scale = model.anchor_log_scale + 0.3 * torch.randn(model.anchor_log_scale.shape, generator=gen)
    model.anchor_velocity = 0.05 * torch.randn(model.anchor_velocity.shape, generator=gen)
    model.anchor_fade = model.anchor_fade + 0.5 * torch.randn(model.anchor_fade.shape, generator=gen)
    lo, hi = model.bbox_min.clone(), model.bbox_max.clone()  # some anchors outside the grids' box
    model.bbox_min, model.bbox_max = lo + 0.2 * (hi - lo), hi - 0.2 * (hi - lo)
    if case == "everything":  # an opacity cut far from every opacity: no round-off flips
        opac = reference_frame(model, 8).opacities.sort().values
        gaps = opac[1:] - opac[:-1]
        mid = opac.numel() // 4 + int(gaps[opac.numel() // 4: 3 * opac.numel() // 4].argmax())
        model.cfg.opacity_threshold = float(opac[mid] + opac[mid + 1]) / 2
    return model
