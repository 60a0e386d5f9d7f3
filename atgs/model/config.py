"""Typed configuration of the ATGS model (every field is an ``atgs-train --model.*`` flag).

The trainer's configuration and the presets that fill both live in :mod:`atgs.train.config`;
``atgs.config_dict`` turns either into plain dicts (checkpoints, config.json) and back.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from atgs.config_checks import above, at_least, between, check_fields, one_of

AnchorLayout = Literal["split", "per-keyframe"]


@dataclass
class HashGridConfig:
    """One 4D multi-resolution hash grid F_T,m (Instant-NGP style) and its small MLP."""

    levels: int = 16
    features_per_level: int = 8
    log2_table_size: int = 16
    base_resolution: int = 16
    growth: float = 2.0
    # Resolution of the local-time axis per level is min(spatial resolution, this).
    max_time_resolution: int = 32
    mlp_hidden: int = 128

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        check_fields(self, "--model.hash.", {
            "levels": at_least(1), "features_per_level": at_least(1), "log2_table_size": between(1, 40),
            "base_resolution": at_least(1), "growth": above(0), "max_time_resolution": at_least(1),
            "mlp_hidden": at_least(1)})


@dataclass
class ModelConfig:
    feature_dim: int = 64  # f_a, f_s and f_t dimension
    gaussians_per_anchor: int = 10  # q
    # Keyframes and window. num_keyframes=0 uses the keyframes of the prepared scene.
    num_keyframes: int = 0
    window: int = 7  # W; 0 disables the window (all anchors active at all times)
    # "split": content seen at most keyframes is static, modelled once by always-active anchors,
    # and only moving content gets anchors per keyframe; "per-keyframe": every keyframe's points
    # become that keyframe's anchors (the paper).
    anchor_layout: AnchorLayout = "split"
    static_fraction: float = 0.5  # split: a cell is static if seen at >= this fraction of keyframes
    static_voxel_factor: float = 1.0  # split: voxel of the static anchors relative to the per-keyframe one
    static_keyframe0: bool = True  # per-keyframe: keyframe 0's anchors are always active (authors' code)
    # Temporal segments: M grids; frames_per_segment>0 overrides M with ceil(F/frames_per_segment).
    num_segments: int = 2
    frames_per_segment: int = 0
    hash: HashGridConfig = field(default_factory=HashGridConfig)
    # Spatial grid F_s (dense, trilinear, zero init).
    use_spatial_grid: bool = True
    spatial_resolution: int = 128
    bbox_padding: float = 0.1  # relative padding of the anchor bounding box for F_s / F_T
    # Decoder hidden sizes (two layers each, see SPEC table).
    hidden_opacity: int = 256
    hidden_cov: int = 256
    hidden_color: int = 256
    hidden_offset: int = 512
    # Anchors.
    voxel_size: float = 0.0  # anchor voxel downsampling; 0 = automatic from point spacing
    max_anchors_per_keyframe: int = 0  # 0 = no cap; random subsample above it
    # Extra static anchors sampled uniformly in the scene bounds: sparse CPU point clouds can miss
    # whole surfaces (floors, moving objects); pruning removes the ones that stay transparent.
    random_anchors: int = 0
    # ... but not in the space the keyframe points show to be empty (between a training camera
    # and the points it sees; atgs.model.random_anchors): there they show as floaters in new views.
    carve_random_anchors: bool = True
    opacity_threshold: float = 0.0  # Gaussians below are dropped (Scaffold-GS); code used 0
    frustum_cull: bool = True  # decode only anchors that project near the image
    camera_clearance: float = 0.02
    """No Gaussian within this fraction of the median training-camera-to-scene distance of any
    training camera (its own housing, which it never sees; atgs.geometry.clearance). Held-out cameras
    get none: nothing about them enters training. 0: off."""
    near_fraction: float = 0.05
    """Near plane of every render of the model (training, evaluation, players): this fraction of the
    median distance from the training cameras to the scene centre (atgs.model.near_plane; 0.2 m for
    cameras 4 m away, as the reference 3DGS rasterizer). 0: the fixed 0.01 scene units of before."""
    # Anchor motion (atgs.model.anchor_motion) and the 3D smoothing filter (atgs.model.smoothing):
    # not in the paper; docs/model.md. Checkpoints from before the motion tables load with motion off.
    temporal_fade: bool = False
    """Per-keyframe anchors fade with their distance in time to their keyframe (learned width, capped: no popping)."""
    fade_width: float = 0.6
    """Initial fade width (standard deviation), in keyframe intervals."""
    anchor_velocity: bool = False
    """Per-keyframe anchors move away from their keyframe with a learned velocity."""
    smoothing_3d: float = 0.0
    """Mip-Splatting's 3D filter: variance in squared pixels of the finest training view (0.2 there; 0: off)."""

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Refuse a value outside its range (:mod:`atgs.config_checks`); also the hash grid's."""
        check_fields(self, "--model.", {
            "feature_dim": at_least(1), "gaussians_per_anchor": at_least(1), "num_keyframes": at_least(0),
            "window": at_least(0), "anchor_layout": one_of(AnchorLayout), "static_fraction": between(0, 1),
            "static_voxel_factor": above(0), "num_segments": at_least(1), "frames_per_segment": at_least(0),
            "spatial_resolution": at_least(1), "bbox_padding": at_least(0),
            "hidden_opacity": at_least(1), "hidden_cov": at_least(1), "hidden_color": at_least(1),
            "hidden_offset": at_least(1), "voxel_size": at_least(0, note="0 = automatic"),
            "max_anchors_per_keyframe": at_least(0, note="0 = no cap"), "random_anchors": at_least(0),
            "opacity_threshold": between(0, 1, high_open=True), "camera_clearance": at_least(0, note="0 = off"),
            "near_fraction": between(0, 1, note="0 = the fixed 0.01", high_open=True),
            "fade_width": above(0), "smoothing_3d": at_least(0, note="0 = off")})
        self.hash.validate()
