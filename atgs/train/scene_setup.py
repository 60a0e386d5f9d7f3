"""What the trainer takes from the scene before its first step: the settings the scene decides
(background, camera exposure), the initial model, the space the training cameras prove empty and
the anchors' starting velocities. Each is one function; :class:`atgs.train.trainer.Trainer` calls
them from its set-up, in order."""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
import torch

from atgs.device import DeviceError
from atgs.free_space import FreeSpace
from atgs.model.atgs_model import ATGSModel
from atgs.progress import progress_bar
from atgs.train.background import resolve_background
from atgs.train.exposure import measure_scene_exposure
from atgs.train.scene_flow import grey_of, initial_velocities

if TYPE_CHECKING:
    from atgs.cameras import Camera
    from atgs.model.config import ModelConfig
    from atgs.render.environment import EnvironmentMap
    from atgs.train.config import TrainConfig
    from atgs.train.trainer import SceneData


def check_backend(device: torch.device, backend: str) -> None:
    """Refuse a ``--train.render-backend`` that cannot rasterize tensors on ``device``."""
    if backend == "cpu" and device.type != "cpu":
        raise DeviceError(f"--train.render-backend cpu rasterizes CPU tensors only, but training runs on {device}; "
                          "use --train.render-backend auto, or --device cpu")
    if backend == "cuda" and device.type != "cuda":
        raise DeviceError("--train.render-backend cuda needs CUDA tensors; use --device cuda, "
                          "or --train.render-backend auto")


def settings_from_scene(scene: "SceneData", cfg: "TrainConfig", environment: "EnvironmentMap | None"
                        ) -> tuple["TrainConfig", "EnvironmentMap | None", np.ndarray | None]:
    """``cfg`` with what it leaves to the scene resolved once, for the whole run (a checkpoint
    carries the result): the background colour (and map by direction) from the training images,
    and ``camera_exposure`` "auto" as "on" or "off" from the training cameras' measured
    brightness. Returns (cfg, environment map, measured exposure (train cameras, 3) or None);
    ``environment``: a resumed run's own map, kept unless the images replace it."""
    measured = None
    if cfg.background_from_images:
        colour, environment = resolve_background(scene, list(scene.train_indices),
                                                 cfg.background_by_direction and not cfg.random_background)
        cfg = replace(cfg, background=colour)
    if cfg.camera_exposure == "auto":
        measured = measure_scene_exposure(scene)
        spread = float(np.nanmax(np.abs(np.log(measured)), initial=0.0))
        cfg = replace(cfg, camera_exposure="on" if spread > cfg.exposure_threshold else "off")
    return cfg, environment, measured


def _bounds(scene: "SceneData") -> torch.Tensor | None:
    b = scene.bounds
    # on the CPU: the model is initialised there and moved afterwards
    return None if b is None else torch.as_tensor(np.asarray(b, dtype=np.float32), device="cpu").reshape(2, 3)


def model_from_scene(scene: "SceneData", model_cfg: "ModelConfig", train_idx: list[int], seed: int,
                     segments: range | None = None) -> ATGSModel:
    """A new model from the scene's keyframe and motion points, built on the CPU (the same
    initialisation on every device; the trainer moves it). ``segments``: only these segments'
    per-segment tables (ATGSModel)."""
    def cpu(values, dtype) -> torch.Tensor:
        return torch.as_tensor(np.asarray(values, dtype=dtype), device="cpu")

    return ATGSModel.from_points(
        model_cfg, cpu(scene.points, np.float32), cpu(scene.point_keyframes, np.int64), list(scene.keyframes),
        scene.num_frames, scene.fps, list(scene.cameras), [scene.cameras[i] for i in train_idx],
        seed=seed, bounds=_bounds(scene), motion_points=cpu(scene.motion_points, np.float32),
        motion_point_keyframes=cpu(scene.motion_point_keyframes, np.int64),
        motion_keyframes=list(scene.motion_keyframes), segments=segments)


def free_space_of(scene: "SceneData", cams: "list[Camera]", device: torch.device) -> FreeSpace:
    """The space ``cams`` prove empty: in front of the scene's measured keyframe points (not its
    fill; all keyframes at once, so anything a moving object occupies at one keyframe stays
    non-empty) and its motion points."""
    pts = np.asarray(scene.points, np.float64)
    pts = pts[np.asarray(scene.measured_points, bool)]
    motion = np.asarray(scene.motion_points, np.float64).reshape(-1, 3)
    return FreeSpace.of(cams, np.concatenate([pts, motion]), device=device)


def velocities_from_flow(model: ATGSModel, scene: "SceneData", train_idx: list[int], progress: bool = True
                         ) -> dict | None:
    """Start the per-keyframe anchors' velocities from the training images' optical flow
    (atgs.train.scene_flow); anchors it cannot measure keep 0. Returns its statistics (anchors
    tracked / measured / given a velocity), None when there is nothing to measure."""
    m = model
    if m.num_keyframes < 2 or not bool((m.anchor_keyframe >= 0).any()) or len(train_idx) < 2:
        return None
    cams = [scene.cameras[i] for i in train_idx]
    bar = progress_bar(m.num_keyframes, "scene flow", unit="keyframe", enabled=progress)

    def grey(ci: int, f: int) -> torch.Tensor:
        return grey_of(scene.image_uint8(train_idx[ci], f))

    def step(k: int, total: int) -> None:
        bar.update(k - bar.n)

    with torch.no_grad():
        vel, stats = initial_velocities(m.anchor_mu.cpu(), m.anchor_keyframe.cpu(), m.voxel_size,
                                        m.timeline.keyframe_frames(), m.num_frames, cams, grey,
                                        progress=step)
        m.anchor_velocity.copy_(vel.to(m.anchor_velocity.device))
    bar.update(bar.total - bar.n)
    bar.close()
    return stats
