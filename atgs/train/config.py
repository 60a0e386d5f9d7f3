"""Typed configuration of the trainer, and the presets that fill it and the model's.

Every field is a command-line flag of ``atgs-train`` (tyro): ``--train.*`` here, ``--model.*`` in
:class:`atgs.model.config.ModelConfig`. :func:`preset` maps a preset name to a (model, train)
pair: ``paper`` uses the paper's sizes (GPU scale), the ``cpu-*`` presets trade quality for
speed on a small CPU, ``tiny`` is for tests. Each config checks its values when built
(:mod:`atgs.config_checks`); the settings that count steps follow the step count by the rule of
:mod:`atgs.train.step_schedule`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal, get_args

from atgs.config_checks import ConfigError, above, at_least, between, check_fields, each, one_of
from atgs.model.config import HashGridConfig, ModelConfig
from atgs.train.step_schedule import SCHEDULE_SETTINGS, ScheduleSetting, schedule_for

PresetName = Literal["cpu-fast", "cpu", "cpu-accurate", "paper", "tiny"]
PRESET_NAMES: tuple[str, ...] = get_args(PresetName)
DEFAULT_PRESET: PresetName = "cpu"
PRESET_HELP: dict[str, str] = {  # (atgs-train --help lists them)
    "cpu-fast": "a 5-minute budget, the smallest CPU model",
    "cpu": "a 20-minute budget on a CPU (the default)",
    "cpu-accurate": "a 60-minute budget, the largest CPU model",
    "paper": "the paper's sizes and 30,000 steps, for a GPU (--device cuda)",
    "tiny": "for tests: a few seconds end to end",
}
VolumeReduction = Literal["sum", "mean", "mean-voxel"]
CameraExposure = Literal["auto", "on", "off"]
Partition = Literal["views", "time", "both"]  # what several workers split (atgs.train.distributed, atgs.train.time_partition)
LOSS_WEIGHT = at_least(0, "a loss weight", "0 = off")


@dataclass
class DensifyConfig:
    enabled: bool = True
    start: int = 500
    stop_fraction: float = 0.6  # stop growing/pruning after this fraction of iterations
    interval: int = 100
    grad_threshold: float = 2e-4  # on NDC-scaled screen-space gradient norms (as 3DGS)
    levels: int = 3
    init_factor: int = 16
    hierarchy_factor: int = 4
    success_threshold: float = 0.8
    min_opacity: float = 0.005
    max_anchors: int = 200_000
    # After the last step, drop anchors that never contributed since densification stopped.
    final_prune: bool = True

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        check_fields(self, "--train.densify.", {
            "start": at_least(0), "stop_fraction": between(0, 1), "interval": at_least(1),
            "grad_threshold": at_least(0), "levels": at_least(1), "init_factor": at_least(1),
            "hierarchy_factor": at_least(1), "success_threshold": at_least(0), "min_opacity": at_least(0),
            "max_anchors": at_least(0)})


@dataclass
class LRConfig:
    anchor_feature: float = 0.0075
    spatial_grid: float = 0.0075
    anchor_scaling: float = 0.007
    offset_init: float = 8e-3
    offset_final: float = 5e-5
    opacity_init: float = 2e-3
    opacity_final: float = 2e-5
    cov: float = 4e-3
    color_init: float = 8e-3
    color_final: float = 5e-5
    # Temporal grids: lr * scene extent; each grid decays with its own visit count.
    temporal_init: float = 2e-4
    temporal_final: float = 2e-6
    temporal_mlp_init: float = 2e-3
    temporal_mlp_final: float = 2e-5
    anchor_velocity: float = 1e-3
    """Anchor velocities (--model.anchor-velocity), times the scene extent (world units per keyframe interval)."""
    anchor_fade: float = 0.01
    """Anchor fade widths (--model.temporal-fade), on their log."""
    moving_anchors: float = 1.0
    """Factor on the learning rates of the anchors of one keyframe (feature, scale, velocity, fade):
    they are trained only by the views of their time span, the static anchors by every view.
    Measured in docs/training.md ("Learning rates at CPU step counts"); 1 = the same as static."""
    exposure: float = 1e-3
    """Per-camera exposure gains (on their log) and biases (--train.camera-exposure); constant."""
    warmup_steps: int = 1000
    """Every learning rate ramps up from warmup-start times its value over these first steps."""
    warmup_start: float = 0.1
    """Factor of the learning rates at the first step (see warmup-steps)."""

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        rate = at_least(0, "a learning rate")
        # the temporal grids' rates decay log-linearly (atgs.train.schedule): 0 has no logarithm
        decaying = above(0, "a learning rate that decays log-linearly")
        check_fields(self, "--train.lr.", {
            "anchor_feature": rate, "spatial_grid": rate, "anchor_scaling": rate, "offset_init": rate,
            "offset_final": rate, "opacity_init": rate, "opacity_final": rate, "cov": rate,
            "color_init": rate, "color_final": rate, "temporal_init": decaying, "temporal_final": decaying,
            "temporal_mlp_init": decaying, "temporal_mlp_final": decaying, "anchor_velocity": rate,
            "anchor_fade": rate, "moving_anchors": above(0, "a factor on learning rates"), "exposure": rate,
            "warmup_steps": at_least(0), "warmup_start": between(0, 1)})


@dataclass
class TrainConfig:
    iterations: int = 30_000
    # Time budget in minutes: > 0 sizes `iterations` (and every interval of the schedule) from the
    # measured step time so that training ends on time (atgs.train.budget); 0 runs `iterations`.
    minutes: float = 0.0
    views_per_step: int = 1  # balanced: views of one step cycle over the temporal segments
    # Cameras rendered per view: one frame is decoded once (for the union of their frusta) and
    # rendered from this many distinct training cameras; decoding is most of a CPU step, so more
    # cameras per frame buy more images per second (docs/training.md measures the trade).
    cameras_per_frame: int = 1
    resolution_scale: float = 1.0  # image downscale for training (0.5 = half resolution)
    lambda_ssim: float = 0.2
    lambda_volume: float = 0.001
    # "sum" (paper), "mean" (authors' code), or "mean-voxel": the mean of prod(scale / voxel),
    # free of the scene's units (atgs.train.losses.volume_loss; measured in docs/training.md,
    # "Random anchors, the volume loss and the offset regulariser on a real capture").
    volume_reduction: VolumeReduction = "sum"
    # Not in the paper: keeps each Gaussian within `offset_free` voxels of its anchor (a squared
    # hinge, atgs.train.losses.offset_loss); 0 = off. Measured in docs/training.md (same section
    # as the volume loss).
    lambda_offset: float = 0.0
    offset_free: float = 1.0
    # Not in the paper: depth distortion (atgs.train.losses.depth_distortion), log(1 + v / voxel^2)
    # of the variance v of each ray's depth; pulls semi-transparent slabs into thin surfaces.
    # 0 = off. Measured in docs/training.md ("Window and background").
    lambda_distortion: float = 0.0
    # Not in the paper: edge-aware second-order smoothness of the rendered inverse depth
    # (atgs.train.losses.depth_smoothness), zero on planes; gives what one training camera sees
    # the depth of its neighbours. 0 = off. Measured in docs/training.md ("Depth smoothness").
    lambda_depth_smooth: float = 0.0
    depth_smooth_edge: float = 10.0  # the image-edge weight's sharpness: exp(-edge * colour change)
    # Not in the paper: the mean opacity of the Gaussians standing in space the measured keyframe
    # points prove empty (atgs.train.losses.free_space_loss, atgs.free_space); keeps floaters off
    # the space between the cameras and the surfaces. 0 = off. Measured in docs/training.md
    # ("Free space").
    lambda_free_space: float = 0.0
    # Not in the paper: the opacity each training ray accumulates in front of the depth its
    # camera measured there (atgs.train.losses.ray_free_space_loss, atgs.ray_free_space), for
    # semi-transparent fog in space the training cameras see through. Off by default: at 0.1,
    # side by side on eight layouts, the held-out figures moved by -1.2 to +0.4 dB, and by
    # -0.8 dB on the synthetic capture stage it was made for; on a real 31-camera dome by
    # -0.10 dB, where the model without it already leaves 0.07 % of the measured rays' opacity
    # in front of their depth (docs/training.md, "Free space along each ray"). 0 = off.
    lambda_ray_free_space: float = 0.0
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Background colour the Gaussians are composited over (RGB in [0, 1]), unless
    --train.background-from-images replaces it."""
    # Train (and evaluate) over a colour taken from the training images instead of `background`:
    # the backdrop's colour when the images' borders are one uniform colour, else the images' mean
    # colour. What no training camera sees has no Gaussians; the mean is the least-squares guess
    # for it, where black is the worst one (docs/training.md, "Window and background").
    background_from_images: bool = True
    # With it, not one colour but one per direction (atgs.train.background): each ray's background
    # is the mean colour the training images show in about its direction, so what lies just
    # beyond the cameras' frames gets the colour framed next to it. Not with a uniform backdrop.
    # Measured in docs/training.md ("Background by direction").
    background_by_direction: bool = True
    random_background: bool = False  # a random colour per step; evaluation still renders over `background`
    # Not in the paper: start the per-keyframe anchors' velocities (--model.anchor-velocity) from
    # the training images' optical flow (atgs.train.scene_flow) instead of 0; the set-up time is
    # paid from a --train.minutes budget. Measured in docs/training.md ("Velocities from optical flow").
    velocity_from_flow: bool = True
    # Not in the paper: a learned gain and bias per colour channel for each training camera, for
    # rigs whose cameras are exposed differently (atgs.train.exposure). Held-out cameras and the
    # viewer render the training cameras' average exposure. "auto": on when the gains measured
    # from the keyframe points before training differ from 1 by more than `exposure_threshold`
    # (the resolved "on"/"off" is saved with the run). Measured in docs/training.md.
    camera_exposure: CameraExposure = "off"
    exposure_threshold: float = 0.03
    exposure_start_measured: bool = True  # learned gains start at the measured ones (else at 1)
    # Not in the paper: DropGaussian (atgs.train.dropout). Each step hides a random fraction of the
    # Gaussians, rising linearly from 0 to this over the run, and scales the others' opacities to
    # keep the coverage; a remedy for over-fitting sparse rigs. 0 = off. Measured in docs/training.md.
    drop_gaussians: float = 0.0
    grad_clip: float = 10.0
    adam_eps: float = 1e-15
    max_bad_steps: int = 50  # consecutive non-finite losses before giving up
    lr: LRConfig = field(default_factory=LRConfig)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    eval_every: int = 1000
    eval_max_frames: int = 8  # frames per test camera in periodic evaluation
    save_every: int = 1000
    image_cache_mb: int = 1024  # uint8 LRU cache of training images
    seed: int = 0
    threads: int = 0  # torch threads while the trainer works (restored after); 0 = torch's default
    # Several workers: "views" shares each step's views (every worker holds the whole model);
    # "time" gives each a block of time segments with their tables and anchors; "both" gives
    # each of time_groups groups of workers a block, whose views the group's workers share
    # (docs/training.md, "Several workers"). One process ignores them.
    partition: Partition = "views"
    time_groups: int = 0  # --train.partition both: blocks of time segments; 0 = one per node (torchrun --nnodes)
    render_backend: str = "auto"  # one of atgs.render.BACKENDS
    fixed_schedule: tuple[ScheduleSetting, ...] = SCHEDULE_SETTINGS
    """Schedule settings kept as given at any step count; the others are sized from the step count
    (--train.iterations, or the steps a --train.minutes budget affords) by atgs.train.step_schedule. paper: all
    of them; the CPU presets: none. atgs-train adds the ones given as flags."""

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Refuse a value outside its range (:mod:`atgs.config_checks`), nested configs included."""
        from atgs.render.api import BACKENDS  # (the renderer owns its backends; imported when checked)

        check_fields(self, "--train.", {
            "iterations": at_least(1, "a step count"), "minutes": at_least(0, "a time budget", "0 = none"),
            "views_per_step": at_least(1), "cameras_per_frame": at_least(1), "resolution_scale": above(0),
            "lambda_ssim": between(0, 1, "the weight of SSIM against L1"), "lambda_volume": LOSS_WEIGHT,
            "volume_reduction": one_of(VolumeReduction), "lambda_offset": LOSS_WEIGHT, "offset_free": at_least(0),
            "lambda_distortion": LOSS_WEIGHT, "lambda_depth_smooth": LOSS_WEIGHT, "depth_smooth_edge": at_least(0),
            "lambda_free_space": LOSS_WEIGHT, "lambda_ray_free_space": LOSS_WEIGHT, "background": each(between(0, 1)),
            "camera_exposure": one_of(CameraExposure), "exposure_threshold": at_least(0),
            "drop_gaussians": between(0, 1, "a fraction of the Gaussians", high_open=True),
            "grad_clip": at_least(0, note="0 = off"), "adam_eps": at_least(0), "max_bad_steps": at_least(0),
            "eval_every": at_least(0, note="0 = off"), "eval_max_frames": at_least(1),
            "save_every": at_least(0, note="0 = off"), "image_cache_mb": at_least(0),
            "threads": at_least(0, note="0 = torch's default"), "partition": one_of(Partition),
            "time_groups": at_least(0, note="0 = one per node"), "render_backend": one_of(BACKENDS),
            "fixed_schedule": each(one_of(SCHEDULE_SETTINGS))})
        self.lr.validate()
        self.densify.validate()


def _cpu_model(**kw) -> ModelConfig:
    base = dict(
        feature_dim=32,
        gaussians_per_anchor=5,
        num_segments=2,
        spatial_resolution=32,
        hash=HashGridConfig(levels=8, features_per_level=2, log2_table_size=14, base_resolution=8,
                            growth=1.5, max_time_resolution=16, mlp_hidden=64),
        hidden_opacity=64, hidden_cov=64, hidden_color=64, hidden_offset=128,
        opacity_threshold=0.005,
        random_anchors=3000,
        # anchor motion (docs/model.md): +4.5 dB held out at 8 minutes on the built-in scene
        temporal_fade=True,
        anchor_velocity=True,
    )
    base.update(kw)
    return ModelConfig(**base)


# Growth threshold of the cpu-fast and cpu presets: twice the paper's. At their step counts an
# anchor grown costs more steps than it returns (built-in scene, 8-minute runs, docs/training.md:
# 2e-4 -> 20.7 dB, 4e-4 -> 20.9 dB, 1e-4 -> 17.2 dB held out).
CPU_GROW_THRESHOLD = 4e-4


def _cpu_train(iterations: int, grow_threshold: float = DensifyConfig.grad_threshold, **kw) -> TrainConfig:
    base = dict(densify=DensifyConfig(grad_threshold=grow_threshold),
                # the schedule follows the step count (atgs.train.step_schedule)
                fixed_schedule=(),
                # the paper's sum over Gaussians in world units shrank Gaussians on a real capture;
                # the mean in voxel units: +0.6 / +2.7 dB there, +0.07 dB built in (docs/training.md)
                volume_reduction="mean-voxel", lambda_volume=0.01,
                # Gaussians within a voxel of their anchor: +1.9 to +3.6 dB on the real capture,
                # +0.01 dB built in (docs/training.md)
                lambda_offset=0.01,
                # planar depth where one camera sees a surface: +0.25 / +0.43 dB held out on the
                # built-in scene at 1,200 steps, seeds 0 / 1 (docs/training.md, "Depth smoothness")
                lambda_depth_smooth=0.5,
                # per-camera exposure where the rig needs it: +1.1 to +4.8 dB on the real capture;
                # off on the built-in scene, whose cameras are exposed alike (docs/training.md)
                camera_exposure="auto")
    base.update(kw)
    return schedule_for(TrainConfig(**base), iterations)


def preset(name: str, iterations: int | None = None, minutes: float | None = None
           ) -> tuple[ModelConfig, TrainConfig]:
    """(model, train) configuration of a named preset; see :data:`PRESET_NAMES`.

    The CPU presets train for a time budget (``train.minutes``: cpu-fast 5, cpu 20, cpu-accurate
    60), their step count sized from the measured step time; ``paper`` runs a fixed 30,000 steps.
    ``iterations`` fixes the step count instead (no budget), its schedule sized by
    :func:`~atgs.train.step_schedule.schedule_for`; ``minutes`` sets the budget."""
    model, train = _preset(name)
    if iterations is not None:
        train = schedule_for(replace(train, minutes=0.0), iterations)
    if minutes is not None:
        train = replace(train, minutes=float(minutes))
    return model, train


def _preset(name: str) -> tuple[ModelConfig, TrainConfig]:
    if name == "paper":
        return ModelConfig(), TrainConfig()
    if name == "cpu-fast":
        return _cpu_model(), _cpu_train(2000, minutes=5.0, grow_threshold=CPU_GROW_THRESHOLD)
    if name == "cpu":
        return (_cpu_model(feature_dim=48, gaussians_per_anchor=8, spatial_resolution=48,
                           hash=HashGridConfig(levels=12, features_per_level=2, log2_table_size=15,
                                               base_resolution=8, growth=1.5, max_time_resolution=16,
                                               mlp_hidden=64),
                           hidden_opacity=96, hidden_cov=96, hidden_color=96, hidden_offset=192),
                _cpu_train(5000, minutes=20.0, grow_threshold=CPU_GROW_THRESHOLD))
    if name == "cpu-accurate":
        return (_cpu_model(feature_dim=64, gaussians_per_anchor=10, spatial_resolution=64,
                           hash=HashGridConfig(levels=16, features_per_level=4, log2_table_size=17,
                                               base_resolution=8, growth=1.5, max_time_resolution=32,
                                               mlp_hidden=128),
                           hidden_opacity=128, hidden_cov=128, hidden_color=128, hidden_offset=256),
                _cpu_train(15000, minutes=60.0))
    if name == "tiny":  # unit tests: a few seconds end to end
        return (_cpu_model(feature_dim=8, gaussians_per_anchor=3, spatial_resolution=8,
                           hash=HashGridConfig(levels=2, features_per_level=2, log2_table_size=10,
                                               base_resolution=4, growth=2.0, max_time_resolution=4,
                                               mlp_hidden=16),
                           hidden_opacity=16, hidden_cov=16, hidden_color=16, hidden_offset=16,
                           random_anchors=0),
                _cpu_train(40, eval_every=0, save_every=0, threads=1))
    raise ConfigError(f"preset {name!r}: use one of {', '.join(PRESET_NAMES)}")
