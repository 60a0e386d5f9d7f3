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
from atgs.geometry.free_space import FreeSpace
from atgs.model.atgs_model import ATGSModel
from atgs.progress import progress_bar
from atgs.train.background import resolve_background
from atgs.train.exposure import measure_scene_exposure
from atgs.train.scene_flow import grey_of, initial_velocities

if TYPE_CHECKING:
    from collections.abc import Callable

    from atgs.cameras import Camera
    from atgs.geometry.ray_free_space import MeasuredDepths
    from atgs.model.anchor_setup import Spread
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
                     segments: range | None = None, spread: "Spread | None" = None) -> ATGSModel:
    """A new model from the scene's keyframe and motion points, read a keyframe at a time and
    built on the CPU (the same initialisation on every device; the trainer moves it).
    ``segments``: only these segments' per-segment tables (ATGSModel); ``spread``: the workers
    sharing the anchors' set-up (atgs.model.anchor_setup)."""
    return ATGSModel.from_clouds(
        model_cfg, scene.point_cloud, list(scene.keyframes), scene.num_frames, scene.fps, list(scene.cameras),
        [scene.cameras[i] for i in train_idx], seed=seed, bounds=_bounds(scene), motion_cloud=scene.motion_cloud,
        motion_keyframes=list(scene.motion_keyframes), segments=segments, spread=spread)


def free_space_of(scene: "SceneData", cams: "list[Camera]", device: torch.device) -> FreeSpace:
    """The space ``cams`` prove empty: in front of the scene's measured keyframe points (not its
    fill; all keyframes at once, so anything a moving object occupies at one keyframe stays
    non-empty) and its motion points, read a keyframe at a time."""
    # (the random anchors' carving, atgs.model.anchor_setup, folds the same grids over the model's
    # point groups instead, fill included: each selection is kept as it was, since changing either
    # changes what a fixed-seed run trains)
    cloud, motion, measured = scene.point_cloud, scene.motion_cloud, scene.measured_counts  # (each built once)
    parts = [(cloud, k, None if measured is None else measured[k]) for k in range(cloud.num_keyframes)]
    parts += [(motion, k, None) for k in range(motion.num_keyframes)]
    return FreeSpace.of_parts(cams, (pc.read(k)[:n] for pc, k, n in parts), device=device)


def measured_depths_of(scene: "SceneData", cams: "list[Camera]", image_of: "Callable[[int, int], np.ndarray]",
                       device: torch.device) -> "MeasuredDepths | None":
    """Each training camera's measured depth per image cell (atgs.geometry.ray_free_space), from the
    scene's measured keyframe points (not its fill) and its motion points, each at the frame it
    was measured at, a keyframe at a time. ``cams``: the training cameras at the training
    resolution; ``image_of(slot, frame)`` reads ``cams[slot]``'s (H, W, 3) uint8 image. None
    when the scene has no measured point."""
    from atgs.geometry.ray_free_space import MeasuredDepths

    cloud, motion, measured = scene.point_cloud, scene.motion_cloud, scene.measured_counts
    sources = [(cloud, k, scene.keyframes[k], None if measured is None else measured[k])
               for k in range(cloud.num_keyframes)]
    sources += [(motion, k, scene.motion_keyframes[k], None) for k in range(motion.num_keyframes)]

    def parts():
        for pc, k, frame, n in sources:
            pts, cols = pc.read_with_colors(k)
            if len(pts[:n]):
                yield int(frame), pts[:n], cols[:n]

    depths = MeasuredDepths.measure(cams, list(parts()), image_of, device)
    return depths if depths.any_measured else None


def velocities_from_flow(model: ATGSModel, scene: "SceneData", train_idx: list[int], progress: bool = True,
                         spread: "Spread | None" = None) -> dict | None:
    """Start the per-keyframe anchors' velocities from the training images' optical flow
    (atgs.train.scene_flow); anchors it cannot measure keep 0. ``spread``: workers (each
    holding the same anchors) that measure every world-th keyframe each and share the results.
    Returns its statistics (anchors tracked / measured / given a velocity), None when there is
    nothing to measure."""
    m = model
    if m.num_keyframes < 2 or not bool((m.anchor_keyframe >= 0).any()) or len(train_idx) < 2:
        return None
    cams = [scene.cameras[i] for i in train_idx]
    several = spread is not None and spread.world > 1
    mine = range(spread.rank, m.num_keyframes, spread.world) if several else range(m.num_keyframes)
    bar = progress_bar(len(mine), "scene flow", unit="keyframe", enabled=progress)

    def grey(ci: int, f: int) -> torch.Tensor:
        return grey_of(scene.image_uint8(train_idx[ci], f))

    def step(k: int, total: int) -> None:
        bar.update(sum(1 for j in mine if j < k) - bar.n)

    with torch.no_grad():
        keyframe = m.anchor_keyframe.cpu()
        vel, stats = initial_velocities(m.anchor_mu.cpu(), keyframe, m.voxel_size, m.timeline.keyframe_frames(),
                                        m.num_frames, cams, grey, progress=step, keyframes=mine)
        if several:  # every worker: the rows of its keyframes from all
            rows = torch.isin(keyframe, torch.tensor(list(mine), dtype=torch.int64, device="cpu")).nonzero().squeeze(1)
            parts = spread.gather_everywhere((rows, vel[rows], stats))
            stats = {key: sum(p[2][key] for p in parts) for key in stats}
            for r, v, _ in parts:
                vel[r] = v
        m.anchor_velocity.copy_(vel.to(m.anchor_velocity.device))
    bar.update(bar.total - bar.n)
    bar.close()
    return stats
