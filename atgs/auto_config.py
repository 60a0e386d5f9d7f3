"""``--auto``: model sizes chosen from what a scene needs (issue 6, "model only what a scene requires").

:func:`choose_config` turns a :class:`atgs.data.motion_measure.MotionStats` into overrides of
:class:`atgs.model.config.ModelConfig` fields, each with the reason it was chosen. The rules are
deliberately simple, monotone and bounded (docs/auto.md):

- ``num_keyframes`` K: one keyframe per turnover time of the moving content, at least one per
  ``max_keyframe_gap`` frames and at least 2 when anything moves; 1 for a static scene. Capped by
  the frame count, the anchor memory budget and (by default) the keyframes the scene was prepared
  with, since model keyframes without scene keyframe points get no anchors.
  Calibration: the paper's K=15 for 300-frame N3DV (turnover ~20 frames) and K=250 for 250-frame
  VRU (turnover ~1 frame).
- ``num_segments`` M: one temporal grid per ``segment_turnovers`` turnover times but never shorter
  than ``min_segment_frames`` frames (the authors' code: one grid per 20-frame clip); 1 when
  static. Same calibration: N3DV M=2, VRU M=12.
- ``hash.log2_table_size``: the base preset's size at ``reference_moving_fraction`` of the pixels
  moving, doubled per doubling of the moving fraction, within [base-4, base+2]; reduced (then M
  reduced) until M tables fit the temporal-grid memory budget.
- ``spatial_resolution``: one grid cell per anchor spacing across the padded anchor box, within
  [8, 256] and the spatial-grid memory budget.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field

from atgs.config_dict import from_dict
from atgs.data.motion_measure import MotionStats, format_stats
from atgs.model.config import ModelConfig

_BYTES = 4  # float32


@dataclass(frozen=True)
class AutoRules:
    """Constants of the ``--auto`` rules (docs/auto.md explains each)."""

    keyframes_per_turnover: float = 1.0
    max_keyframe_gap: int = 60  # frames: objects that appear briefly must meet a keyframe
    max_keyframes: int = 2000
    segment_turnovers: float = 10.0
    min_segment_frames: int = 20  # authors' code: one temporal grid per 20 frames
    max_segments: int = 256
    reference_moving_fraction: float = 0.25  # the base table size suits this much motion
    table_below_base: int = 4  # log2 table size stays within [base - this, base + table_above_base]
    table_above_base: int = 2
    log2_table_bounds: tuple[int, int] = (10, 24)
    spatial_resolution_bounds: tuple[int, int] = (8, 256)
    memory_mb: float = 1024.0  # parameters + Adam moments of anchors, F_s and all F_T
    anchor_share: float = 0.25
    spatial_share: float = 0.25
    temporal_share: float = 0.5
    optimizer_copies: int = 3  # parameter + two Adam moments
    respect_scene_keyframes: bool = True

    def validate(self) -> None:
        if self.keyframes_per_turnover <= 0 or self.segment_turnovers <= 0:
            raise ValueError("keyframes_per_turnover and segment_turnovers must be > 0")
        if self.max_keyframe_gap < 1 or self.min_segment_frames < 1:
            raise ValueError("max_keyframe_gap and min_segment_frames must be >= 1")
        if self.memory_mb <= 0:
            raise ValueError(f"memory_mb must be > 0, got {self.memory_mb}")
        lo, hi = self.spatial_resolution_bounds
        if not 2 <= lo <= hi:
            raise ValueError("spatial_resolution_bounds must satisfy 2 <= lo <= hi")


@dataclass
class AutoChoice:
    """Overrides of ModelConfig fields (nested ones as "hash.log2_table_size"), one reason line
    per overridden knob, the uncapped values the measurement asked for, and a summary of the
    measurement."""

    overrides: dict[str, int] = field(default_factory=dict)
    reasons: list[str] = field(default_factory=list)
    wanted: dict[str, int] = field(default_factory=dict)
    measured: str = ""


def _as_model_config(base: ModelConfig | dict) -> ModelConfig:
    if isinstance(base, ModelConfig):
        return base
    if isinstance(base, dict):
        return from_dict(ModelConfig, base)
    raise TypeError(f"base must be a ModelConfig or a dict, got {type(base).__name__}")


def _hash_grid_bytes(cfg: ModelConfig, log2_table: int) -> int:
    """Bytes of one temporal grid F_T,m (table + its MLP) with optimizer state."""
    h = cfg.hash
    n_in = h.levels * h.features_per_level
    params = h.levels * (2**log2_table) * h.features_per_level
    params += n_in * h.mlp_hidden + h.mlp_hidden + h.mlp_hidden * cfg.feature_dim + cfg.feature_dim
    return params * _BYTES


def choose_keyframes(stats: MotionStats, cfg: ModelConfig, rules: AutoRules) -> tuple[int, int, str]:
    """(K, wanted K, reason)."""
    F = stats.num_frames
    if stats.static or F <= 1:
        want = 1
        why = ("static scene (%.2f%% of pixels ever change): one keyframe, every anchor always active"
               % (100 * stats.moving_fraction)) if F > 1 else "a single frame: one keyframe"
    else:
        by_time = math.ceil(rules.keyframes_per_turnover * F / stats.time_scale)
        by_gap = math.ceil((F - 1) / rules.max_keyframe_gap) + 1
        want = max(2, by_time, by_gap)
        why = (f"moving content turns over every {stats.time_scale:.1f} frames -> "
               f"{rules.keyframes_per_turnover:g} keyframe per turnover over {F} frames = {by_time}")
        if by_gap > by_time:
            why += f"; raised to {by_gap} so that keyframes are at most {rules.max_keyframe_gap} frames apart"
        if want > max(by_time, by_gap):
            why += "; at least 2 when anything moves"
    k = min(want, F, rules.max_keyframes)
    caps = []
    if k < want:
        caps.append(f"the frame count / limit {min(F, rules.max_keyframes)}")
    per_kf = max(1.0, stats.points_per_keyframe)  # voxel downsampling only lowers it
    if cfg.max_anchors_per_keyframe > 0:
        per_kf = min(per_kf, float(cfg.max_anchors_per_keyframe))
    anchor_bytes = (cfg.feature_dim + 6 + 3 + 1) * _BYTES * rules.optimizer_copies
    k_mem = max(1, int(rules.memory_mb * 2**20 * rules.anchor_share // (per_kf * anchor_bytes)))
    if k_mem < k:
        k = k_mem
        caps.append(f"anchor memory ({rules.anchor_share * rules.memory_mb:.0f} MB for "
                    f"~{per_kf:.0f} anchors per keyframe)")
    if rules.respect_scene_keyframes and stats.scene_keyframes < k:
        caps.append(f"the {stats.scene_keyframes} keyframes the scene was prepared with "
                    f"(re-run atgs-prepare with --keyframes {k} to use more)")
        k = max(1, stats.scene_keyframes)
    if caps:
        why += f"; capped at {k} by " + " and ".join(caps)
    return k, want, why


def choose_segments(stats: MotionStats, rules: AutoRules) -> tuple[int, int, str]:
    """(M before the memory check, wanted M, reason)."""
    F = stats.num_frames
    if stats.static or F <= 1:
        return 1, 1, "static scene: one temporal grid" if F > 1 else "a single frame: one temporal grid"
    seg = max(float(rules.min_segment_frames), rules.segment_turnovers * stats.time_scale)
    want = max(1, math.ceil(F / seg))
    m = min(want, F, rules.max_segments)
    why = (f"one temporal grid per {rules.segment_turnovers:g} turnovers ({rules.segment_turnovers:g} x "
           f"{stats.time_scale:.1f} frames), at least {rules.min_segment_frames} frames each -> "
           f"{seg:.0f}-frame segments over {F} frames")
    if m < want:
        why += f"; capped at {m} by the frame count / limit"
    return m, want, why


def choose_table(stats: MotionStats, cfg: ModelConfig, rules: AutoRules) -> tuple[int, int, str]:
    """(log2 table size before the memory check, wanted, reason)."""
    base = cfg.hash.log2_table_size
    lo = max(rules.log2_table_bounds[0], base - rules.table_below_base)
    hi = max(lo, min(rules.log2_table_bounds[1], base + rules.table_above_base))
    if stats.static or stats.num_frames <= 1:
        return lo, lo, f"nothing moves: the smallest table allowed, 2^{lo} (preset 2^{base} - {base - lo})"
    frac = max(stats.moving_fraction, 1e-9)
    want = base + round(math.log2(frac / rules.reference_moving_fraction))
    t = min(hi, max(lo, want))
    why = (f"{100 * stats.moving_fraction:.1f}% of pixels move vs {100 * rules.reference_moving_fraction:.0f}% "
           f"for the preset's 2^{base} -> 2^{want}")
    if t != want:
        why += f", kept within [2^{lo}, 2^{hi}]"
    return t, want, why


def choose_spatial_resolution(stats: MotionStats, cfg: ModelConfig, rules: AutoRules) -> tuple[int, int, str]:
    """(resolution, wanted, reason)."""
    lo, hi = rules.spatial_resolution_bounds
    spacing = cfg.voxel_size if cfg.voxel_size > 0 else stats.point_spacing
    use_bounds = cfg.random_anchors > 0 or stats.points_extent <= 0
    box = stats.extent if use_bounds else stats.points_extent
    if spacing <= 0 or box <= 0:
        r = min(hi, max(lo, cfg.spatial_resolution))
        return r, r, "no point spacing to measure (no points): the preset's resolution"
    padded = box * (1 + 2 * cfg.bbox_padding)
    want = math.ceil(padded / spacing) + 1  # vertices: cells = res - 1
    r = min(hi, max(lo, want))
    src = "voxel_size" if cfg.voxel_size > 0 else "point spacing"
    why = (f"anchor box {padded:.2f} ({'scene bounds' if use_bounds else 'points'} + padding) / "
           f"{src} {spacing:.4f} -> {want} vertices per side")
    if r != want:
        why += f", kept within [{lo}, {hi}]"
    budget = rules.memory_mb * 2**20 * rules.spatial_share
    r_mem = int((budget / (cfg.feature_dim * _BYTES * rules.optimizer_copies)) ** (1.0 / 3.0))
    while (r_mem + 1) ** 3 * cfg.feature_dim * _BYTES * rules.optimizer_copies <= budget:
        r_mem += 1  # exact integer cube root despite float rounding
    while r_mem > lo and r_mem**3 * cfg.feature_dim * _BYTES * rules.optimizer_copies > budget:
        r_mem -= 1
    if r_mem < r:
        r = max(lo, r_mem)
        why += f"; capped at {r} by spatial-grid memory ({budget / 2**20:.0f} MB)"
    if not cfg.use_spatial_grid:
        why += " (the spatial grid is disabled in this configuration)"
    return r, want, why


def choose_config(stats: MotionStats, base: ModelConfig | dict, rules: AutoRules = AutoRules()) -> AutoChoice:
    """Overrides of ``base`` (a ModelConfig or its dict) chosen from the measured ``stats``."""
    rules.validate()
    cfg = _as_model_config(base)
    ch = AutoChoice(measured=format_stats(stats))
    k, k_want, k_why = choose_keyframes(stats, cfg, rules)
    m, m_want, m_why = choose_segments(stats, rules)
    t, t_want, t_why = choose_table(stats, cfg, rules)

    # memory of the M temporal grids: shrink the table first (down to its lower bound), then M
    budget = rules.memory_mb * 2**20 * rules.temporal_share
    t_lo = max(rules.log2_table_bounds[0], cfg.hash.log2_table_size - rules.table_below_base)
    t_lo = min(t_lo, t)
    t0, m0 = t, m
    while t > t_lo and m * _hash_grid_bytes(cfg, t) * rules.optimizer_copies > budget:
        t -= 1
    per = _hash_grid_bytes(cfg, t) * rules.optimizer_copies
    if m * per > budget:
        m = max(1, int(budget // per))
    mem = f"temporal-grid memory ({budget / 2**20:.0f} MB)"
    if t < t0:
        t_why += f"; reduced to 2^{t} to fit {m0} grids in {mem}"
    if m < m0:
        m_why += f"; capped at {m} by {mem}"
    r, r_want, r_why = choose_spatial_resolution(stats, cfg, rules)

    ch.overrides = {"num_keyframes": k, "num_segments": m, "hash.log2_table_size": t, "spatial_resolution": r}
    ch.wanted = {"num_keyframes": k_want, "num_segments": m_want, "hash.log2_table_size": t_want,
                 "spatial_resolution": r_want}
    ch.reasons = [f"num_keyframes = {k}: {k_why}", f"num_segments = {m}: {m_why}",
                  f"hash.log2_table_size = {t}: {t_why}", f"spatial_resolution = {r}: {r_why}"]
    if cfg.frames_per_segment > 0:
        ch.overrides["frames_per_segment"] = 0
        ch.reasons.append(f"frames_per_segment = 0: was {cfg.frames_per_segment}, which would override num_segments")
    return ch


def format_choice(choice: AutoChoice) -> str:
    """The measurement summary and one line per chosen knob, for printing."""
    lines = ["--auto: " + (choice.measured.replace("\n", "\n        ") if choice.measured else "(no measurement)")]
    lines.append("--auto chose:")
    lines += [f"  {r}" for r in choice.reasons]
    return "\n".join(lines)


def apply_overrides(cfg, overrides: dict[str, int | float | bool]):
    """A copy of the config dataclass ``cfg`` with ``overrides`` applied; nested fields as
    "hash.log2_table_size"."""
    out = copy.deepcopy(cfg)
    for key, value in overrides.items():
        obj, parts = out, key.split(".")
        for p in parts[:-1]:
            obj = getattr(obj, p, None)
            if obj is None or not dataclasses.is_dataclass(obj):
                raise ValueError(f"unknown config field {key!r}")
        if parts[-1] not in {f.name for f in dataclasses.fields(obj)}:
            raise ValueError(f"unknown config field {key!r}")
        setattr(obj, parts[-1], value)
    return out
