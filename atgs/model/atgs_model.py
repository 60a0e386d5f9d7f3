"""ATGSModel: time-conditioned anchors + F_s + F_T,m + decoder -> Gaussians at time t.

One decode, two ways of gathering its inputs. Training (:meth:`ATGSModel.decode_frame`) reads the
rows of the anchors it decodes as autograd leaves and decodes only those that may reach its
cameras; inference (:meth:`ATGSModel.gaussians_at`, the player, evaluation and export) takes
them from caches (atgs.model.fast_decode). Both then run the same code: the heads' activations
(atgs.model.decoder.gaussians_from_heads) and :meth:`ATGSModel._drawn` (3D smoothing, temporal
fade, velocity shift, the kept-Gaussians cut).

Large tables (anchor features and scales, F_s, the hash tables, the per-segment temporal MLPs)
are plain tensors updated row-sparsely by :class:`atgs.train.optim.SparseAdam`; a tracked
decode returns the leaves of the rows it touched. The decoder MLPs are an ``nn.Module``.

A model is built on the CPU (the same initialisation whatever the device) and moved with
:meth:`ATGSModel.to`; decoding creates every tensor on the device of the model's tables.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
import math
from typing import get_args, get_type_hints

import numpy as np
import torch

from atgs.cameras import Camera
from atgs.gaussians import Gaussians
from atgs.model.anchor_motion import (MIN_FADE, MOTION_TABLES, fade_weight, faded_and_moved, initial_fade,
                                      keyframe_distance, max_fade_width)
from atgs.geometry.clearance import CameraClearance, clearance_radius
from atgs.geometry.reach import AnchorReach, gaussian_reach, visible_anchors
from atgs.keyframe_cloud import ArrayPointCloud, PointCloud
from atgs.model.anchor_setup import Spread, anchors_from_clouds
from atgs.model.anchors import STATIC, AnchorInit
from atgs.model.config import ModelConfig
from atgs.model.decoder import DecodedGaussians, GaussianDecoder
from atgs.model.fast_decode import DecodeTables, InferenceCache
from atgs.model.grids import HashGrid4D, SpatialGrid
from atgs.model.near_plane import near_plane
from atgs.model.smoothing import filter_variance, sampling_rates, smooth
from atgs.render.constants import NEAR
from atgs.render.environment import EnvironmentMap
from atgs.timeline import Timeline

# Sparse (row-updated) tensors of the model; anchors are rows of the first three.
ANCHOR_TABLES = ("anchor_feature", "anchor_log_scale") + MOTION_TABLES
TEMPORAL_MLP = ("tmlp_w1", "tmlp_b1", "tmlp_w2", "tmlp_b2")
SEGMENT_TABLES = ("hash",) + TEMPORAL_MLP  # per-segment tables: rows of one time segment after another


def segment_rows(name: str, segments: range, rows_per_grid: int) -> range:
    """The rows of ``segments`` in a per-segment table (:data:`SEGMENT_TABLES`) of all segments.
    ``rows_per_grid``: the hash's rows per segment (levels x table size)."""
    per = rows_per_grid if name == "hash" else 1
    return range(segments.start * per, segments.stop * per)
ANCHOR_LAYOUTS: tuple[str, ...] = get_args(get_type_hints(ModelConfig)["anchor_layout"])  # its Literal


@dataclass
class SparseLeaf:
    name: str
    rows: torch.Tensor
    leaf: torch.Tensor


@dataclass
class Decoded:
    gaussians: Gaussians  # the Gaussians passed to the rasterizer
    anchor_ids: torch.Tensor  # (N,) global anchor index of each Gaussian
    slot_ids: torch.Tensor  # (N,) slot in 0..q-1
    active: torch.Tensor  # (A,) global ids of decoded anchors
    raw: DecodedGaussians  # all q Gaussians of each decoded anchor (for statistics)
    segment: int
    sparse: list[SparseLeaf] = field(default_factory=list)
    shift: torch.Tensor | None = None  # (N, 3) the anchor-velocity displacement in the means, if any

    def keyframe_means(self) -> torch.Tensor:
        """The Gaussians' means without the velocity displacement: where they are at their anchor's
        keyframe (anchors grown from them are placed there, since they inherit the velocity)."""
        means = self.gaussians.means.detach()
        return means if self.shift is None else means - self.shift.detach()

    def offsets(self, anchor_mu: torch.Tensor) -> torch.Tensor:
        """(N, 3) each Gaussian's offset from its anchor at the anchor's keyframe (differentiable;
        ``anchor_mu``: the model's (A, 3) anchor positions)."""
        means = self.gaussians.means if self.shift is None else self.gaussians.means - self.shift
        return means - anchor_mu.index_select(0, self.anchor_ids)


def num_segments_for(cfg: ModelConfig, num_frames: int) -> int:
    if cfg.frames_per_segment > 0:
        return max(1, math.ceil(num_frames / cfg.frames_per_segment))
    return max(1, cfg.num_segments)


class ATGSModel:
    def __init__(self, cfg: ModelConfig, timeline: Timeline, cameras: list[Camera], fps: float,
                 anchors: AnchorInit, bbox_min: torch.Tensor, bbox_max: torch.Tensor, extent: float,
                 seed: int = 0, clearance: float = 0.0, segments: range | None = None,
                 draw_hash: bool = True) -> None:
        """``segments``: the per-segment tables (hash grids, temporal MLPs) hold only these
        segments' rows (a worker of the time partition, atgs.train.partition.time_slice): decoding
        then reaches only frames of these segments; None: all of them. ``draw_hash=False``: the
        hash table is left uninitialised, for a loaded one (:meth:`from_state`)."""
        self.cfg, self.timeline = cfg, timeline
        # the first segment of the per-segment tables (their row 0); see ``segments``
        self.first_segment = 0 if segments is None else segments.start
        self.cameras, self.fps, self.extent = list(cameras), float(fps), float(extent)
        self.voxel_size = anchors.voxel_size
        self.test_camera_names: list[str] = []
        # every render of the model culls Gaussians at view z <= near (atgs.model.near_plane);
        # from_clouds sets the scene's, from_state the saved one
        self.near: float = NEAR
        # the RGB training rendered over (its train_config.background): viewers and evaluation use it
        self.background: tuple[float, float, float] = (0.0, 0.0, 0.0)
        # or, when training rendered over a background by direction, that map (it wins over the RGB)
        self.environment: EnvironmentMap | None = None
        self.bbox_min, self.bbox_max = bbox_min.float(), bbox_max.float()
        gen = torch.Generator().manual_seed(seed)
        d = cfg.feature_dim
        self.anchor_mu = anchors.mu.float().contiguous()
        self.anchor_keyframe = anchors.keyframe.long()
        self.anchor_feature = torch.zeros(self.num_anchors, d, device=self.anchor_mu.device)
        self.anchor_log_scale = anchors.log_scale.float().clone()
        # anchor motion (atgs.model.anchor_motion): velocity per keyframe interval, log fade width
        self.anchor_velocity = torch.zeros(self.num_anchors, 3, device=self.anchor_mu.device)
        self.anchor_fade = torch.full((self.num_anchors, 1), self.initial_fade(), device=self.anchor_mu.device)
        # how far each anchor's Gaussians reach (atgs.geometry.reach): measured by the decodes
        self.reach = AnchorReach(self.num_anchors, self.anchor_mu.device)
        # no Gaussian inside a training camera's own housing (atgs.geometry.clearance): the balls
        # are placed when read (:attr:`clearance`), once the held-out cameras are known
        self._clearance = CameraClearance.of_cameras([], clearance, self.anchor_mu.device)
        self._clearance_left_out: tuple[str, ...] | None = None  # the held-out names its balls leave out
        self.spatial = SpatialGrid(cfg.spatial_resolution if cfg.use_spatial_grid else 2, d)
        h = cfg.hash
        M = timeline.num_segments
        self.hash = HashGrid4D(M, h.levels, h.features_per_level, h.log2_table_size, h.base_resolution,
                               h.growth, h.max_time_resolution, generator=gen, grids=segments, draw=draw_hash)
        n_in = h.levels * h.features_per_level

        def uni(shape: tuple[int, ...], fan_in: int) -> torch.Tensor:
            b = 1.0 / math.sqrt(fan_in)
            return (torch.rand(shape, generator=gen, device=gen.device) * 2 - 1) * b

        self.tmlp_w1 = uni((M, n_in, h.mlp_hidden), n_in)
        self.tmlp_b1 = uni((M, h.mlp_hidden), n_in)
        self.tmlp_w2 = uni((M, h.mlp_hidden, d), h.mlp_hidden)
        self.tmlp_b2 = uni((M, d), h.mlp_hidden)
        if segments is not None:
            for name in TEMPORAL_MLP:
                setattr(self, name, getattr(self, name)[segments.start:segments.stop].clone())
        with torch.random.fork_rng():
            torch.manual_seed(seed)
            self.decoder = GaussianDecoder(2 * d, cfg.gaussians_per_anchor, cfg.hidden_opacity,
                                           cfg.hidden_cov, cfg.hidden_color, cfg.hidden_offset)
        # Time-invariant quantities of the inference decode; invalidated by tensor versions.
        self.inference_cache = InferenceCache()
        self._smoothing: tuple | None = None  # (key, variance) of smoothing_variance()

    # --- construction -------------------------------------------------------------------
    @classmethod
    def from_points(cls, cfg: ModelConfig, points: torch.Tensor, point_keyframes: torch.Tensor,
                    scene_keyframes: list[int], num_frames: int, fps: float, cameras: list[Camera],
                    train_cameras: list[Camera] | None = None, seed: int = 0,
                    bounds: torch.Tensor | None = None, motion_points: torch.Tensor | None = None,
                    motion_point_keyframes: torch.Tensor | None = None,
                    motion_keyframes: list[int] | None = None, segments: range | None = None) -> "ATGSModel":
        """:meth:`from_clouds` of points in memory."""
        def cloud(pts, kfs, n: int) -> ArrayPointCloud:
            def arr(x):
                return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
            return ArrayPointCloud(arr(pts), arr(kfs), n)

        motion = None
        if motion_points is not None and motion_keyframes:
            motion = cloud(motion_points, motion_point_keyframes, len(motion_keyframes))
        return cls.from_clouds(cfg, cloud(points, point_keyframes, len(scene_keyframes)), scene_keyframes,
                               num_frames, fps, cameras, train_cameras, seed, bounds, motion,
                               list(motion_keyframes or []), segments)

    @classmethod
    def from_clouds(cls, cfg: ModelConfig, cloud: PointCloud, scene_keyframes: list[int], num_frames: int,
                    fps: float, cameras: list[Camera], train_cameras: list[Camera] | None = None, seed: int = 0,
                    bounds: torch.Tensor | None = None, motion_cloud: PointCloud | None = None,
                    motion_keyframes: list[int] | None = None, segments: range | None = None,
                    spread: Spread | None = None) -> "ATGSModel":
        """Anchors from the scene's keyframe points, read a keyframe at a time
        (atgs.model.anchor_setup; ``spread``: shared by several workers). ``motion_cloud``
        (points on moving content only, at ``motion_keyframes``, atgs.data.moving_points) become
        per-keyframe anchors of the model keyframe nearest their frame; by default the model then
        has as many keyframes as the denser of the two lists."""
        motion_keyframes = list(motion_keyframes or []) if motion_cloud is not None and len(motion_cloud) else []
        K = cfg.num_keyframes if cfg.num_keyframes > 0 else max(len(scene_keyframes), len(motion_keyframes))
        tl = Timeline(num_frames, K, cfg.window, num_segments_for(cfg, num_frames))
        if cfg.anchor_layout not in ANCHOR_LAYOUTS:
            raise ValueError(f"anchor_layout must be one of {ANCHOR_LAYOUTS}, got {cfg.anchor_layout!r}")
        anchors = anchors_from_clouds(cfg, tl, cloud, scene_keyframes, motion_cloud, motion_keyframes,
                                      train_cameras or cameras, bounds, seed, spread)
        lo, hi = anchors.mu.min(0).values, anchors.mu.max(0).values
        size = (hi - lo).clamp_min(1e-3)
        pad = cfg.bbox_padding * size
        centers = np.stack([c.center for c in (train_cameras or cameras)])
        radius = float(np.linalg.norm(centers - centers.mean(0), axis=1).max()) if len(centers) > 1 else 1.0
        # the clearance of the training cameras only: a held-out pose changes nothing trained
        train = list(train_cameras or cameras)
        clear = clearance_radius(train, anchors.mu.median(0).values.cpu().numpy(), cfg.camera_clearance)
        model = cls(cfg, tl, cameras, fps, anchors, lo - pad, hi + pad, 1.1 * max(radius, 1e-3), seed, clear,
                    segments)
        model.test_camera_names = [c.name for c in cameras if c.name not in {t.name for t in train}]
        # from the training cameras only: no held-out camera's position changes what is drawn
        model.near = near_plane(train, anchors.mu.median(0).values.cpu().numpy(), cfg.near_fraction)
        return model

    # --- public API (docs/ARCHITECTURE.md) ----------------------------------------------------
    @property
    def num_frames(self) -> int:
        return self.timeline.num_frames

    @property
    def num_keyframes(self) -> int:
        return self.timeline.num_keyframes

    @property
    def num_segments(self) -> int:
        return self.timeline.num_segments

    @property
    def decodable_frames(self) -> range:
        """The frames of the segments the per-segment tables hold (all frames but on a worker
        of the time partition)."""
        tl, first = self.timeline, self.first_segment
        held = [r for r in (tl.frames_of_segment(m) for m in range(first, first + self.hash.num_grids)) if len(r)]
        return range(held[0].start, held[-1].stop) if held else range(0)  # (segments may hold no frame)

    @property
    def num_anchors(self) -> int:
        return int(self.anchor_mu.shape[0])

    @property
    def device(self) -> torch.device:
        """Where the model's tables live (and where it decodes)."""
        return self.anchor_mu.device

    def to(self, device: torch.device | str) -> "ATGSModel":
        """Move every table, grid, MLP and the decoder to ``device`` in place and return the
        model (as ``nn.Module.to``); the inference cache is emptied (its tensors are rebuilt on
        the device at the next decode)."""
        device = torch.device(device)
        if device == self.device:
            return self
        for name in ("anchor_mu", "anchor_keyframe", "bbox_min", "bbox_max"):
            setattr(self, name, getattr(self, name).to(device))
        for name, table in self.sparse_tensors().items():
            self.set_sparse_tensor(name, table.to(device))
        self.decoder.to(device)
        self.reach.to(device)
        self._clearance = self._clearance.to(device)
        self.inference_cache.clear()
        return self

    @property
    def clearance(self) -> CameraClearance:
        """The balls no Gaussian may sit in: around the training cameras (the model's cameras
        less ``test_camera_names``; a held-out camera's pose never changes what is drawn), of the
        radius the model was built with; rebuilt when the held-out cameras change."""
        names = tuple(self.test_camera_names)
        if self._clearance_left_out != names:
            train = [c for c in self.cameras if c.name not in set(names)]
            self._clearance = CameraClearance.of_cameras(train, self._clearance.radius, self.device)
            self._clearance_left_out = names
        return self._clearance

    def initial_fade(self) -> float:
        return initial_fade(self.cfg.fade_width, self.timeline)

    @property
    def has_motion(self) -> bool:
        return bool(self.cfg.temporal_fade or self.cfg.anchor_velocity)

    def fade_of(self, f: int, anchors: torch.Tensor, log_fade: torch.Tensor | None = None,
                distances: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(keyframe distances, fade weights) of ``anchors`` (global ids) at frame f; weights are
        1 without ``temporal_fade``. ``log_fade``: the anchors' stored fades (a tracked leaf);
        ``distances``: their keyframe distances, when already known."""
        d = keyframe_distance(self.timeline, f, self.anchor_keyframe.index_select(0, anchors)) \
            if distances is None else distances
        if not self.cfg.temporal_fade:
            return d, torch.ones_like(d)
        lf = self.anchor_fade.index_select(0, anchors) if log_fade is None else log_fade
        return d, fade_weight(lf, d, max_fade_width(self.timeline))

    def fade_cut(self) -> float:
        """Anchors whose fade is below this are not decoded (their Gaussians cannot show)."""
        return max(MIN_FADE, float(self.cfg.opacity_threshold))

    def faded_in(self, f: int, anchors: torch.Tensor) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """(positions in ``anchors`` (global ids) of those whose fade at frame f reaches
        :meth:`fade_cut`, their keyframe distances); (None, None) without ``temporal_fade``:
        every anchor shows. Both decodes skip the others."""
        if not self.cfg.temporal_fade:
            return None, None
        dist, w = self.fade_of(f, anchors)
        shown = (w >= self.fade_cut()).nonzero().squeeze(1)
        return shown, dist.index_select(0, shown)

    def smoothing_variance(self) -> torch.Tensor | None:
        """(A,) variance of each anchor's 3D smoothing filter (atgs.model.smoothing) from the
        training cameras (the model's cameras less ``test_camera_names``); None when off. Cached
        until the anchors or the held-out cameras change."""
        if self.cfg.smoothing_3d <= 0:
            return None
        mu, names = self.anchor_mu, tuple(self.test_camera_names)
        if self._smoothing is not None:
            (ref, version, held_out, near), var = self._smoothing
            if ref is mu and version == mu._version and held_out == names and near == self.near:
                return var
        train = [c for c in self.cameras if c.name not in names] or self.cameras
        # (a camera sees an anchor beyond the near plane it renders with)
        var = filter_variance(sampling_rates(mu, train, self.near), float(self.cfg.smoothing_3d))
        self._smoothing = ((mu, mu._version, names, self.near), var)
        return var

    def window_at(self, t: float) -> tuple[int, int]:
        return self.timeline.window_at(t)

    def gaussians_at(self, t: float) -> Gaussians:
        """All Gaussians at normalized time t (clamped to [0, 1]); the cached inference decode
        (atgs.model.fast_decode), equal to the training decode up to float32 round-off."""
        f = self.timeline.frame_at(t)
        m, tau = self.timeline.segment_at(t)
        return self._decode_cached(f, m, tau)

    def gaussians_at_frame(self, f: int) -> Gaussians:
        tl = self.timeline
        return self._decode_cached(f, tl.segment_of_frame(f), tl.local_time_of_frame(f))

    def gaussians_at_frame_reference(self, f: int) -> Gaussians:
        """The uncached decode of frame f (the training path without autograd), for tests."""
        tl = self.timeline
        with torch.no_grad():
            return self._decode(f, tl.segment_of_frame(f), tl.local_time_of_frame(f), None, track=False).gaussians

    def decode_frame(self, f: int, camera: Camera | Sequence[Camera] | None = None, track: bool = True) -> Decoded:
        """Decode frame f for training (``track``: sparse leaves for the optimizer); with
        cameras, only the anchors whose Gaussians may reach their frusta (the union for several;
        :meth:`visible_anchors`) are decoded."""
        tl = self.timeline
        return self._decode(f, tl.segment_of_frame(f), tl.local_time_of_frame(f), camera, track)

    # --- decoding -----------------------------------------------------------------------------
    def active_anchors(self, f: int) -> torch.Tensor:
        lo, hi = self.timeline.window_of_frame(f)
        k = self.anchor_keyframe
        mask = ((k >= lo) & (k <= hi)) | (k == STATIC)
        if self.cfg.static_keyframe0 and self.cfg.anchor_layout == "per-keyframe":
            mask |= k == 0
        return mask

    def visible_anchors(self, f: int, cams: Sequence[Camera], candidates: torch.Tensor | None = None,
                        margin: float = 0.15) -> torch.Tensor:
        """(A,) mask: anchors (of the ``candidates`` mask, default all) whose Gaussians may reach
        one of ``cams`` at frame f (the sphere of their measured reach about their centre at f
        against the frustum and the rasterizer's near plane; atgs.geometry.reach)."""
        ids = torch.arange(self.num_anchors, device=self.device) if candidates is None else candidates.nonzero().squeeze(1)
        centres = self.anchor_mu.index_select(0, ids)
        if self.cfg.anchor_velocity:
            d = keyframe_distance(self.timeline, f, self.anchor_keyframe.index_select(0, ids))
            centres = centres + self.anchor_velocity.index_select(0, ids) * d[:, None]
        out = torch.zeros(self.num_anchors, dtype=torch.bool, device=self.device)
        out[ids] = visible_anchors(centres, self.reach.bound(ids), list(cams), margin, self.near)
        return out

    def refresh_reach(self) -> int:
        """Measure the reach of every anchor no decode has measured since the last refresh (each
        at its keyframe's frame, static ones at the first keyframe's), then settle the bounds
        (atgs.geometry.reach). Returns how many anchors were measured here."""
        stale = torch.zeros(self.num_anchors, dtype=torch.bool, device=self.device)
        stale[self.reach.stale()] = True
        n = int(stale.sum())
        # (a model holding some segments only: the nearest frame it decodes)
        lo, hi = self.decodable_frames.start, self.decodable_frames.stop - 1
        frames = [min(max(f, lo), hi) for f in self.timeline.keyframe_frames()]
        with torch.no_grad():
            for j, f in enumerate(frames):
                own = (self.anchor_keyframe == j) | ((self.anchor_keyframe == STATIC) if j == 0 else False)
                if bool((stale & own).any()):
                    tl = self.timeline
                    self._decode(f, tl.segment_of_frame(f), tl.local_time_of_frame(f), None, False, only=stale & own)
        self.reach.settle()
        return n

    def normalized_positions(self, mu: torch.Tensor) -> torch.Tensor:
        return (mu - self.bbox_min) / (self.bbox_max - self.bbox_min)

    def _decode(self, f: int, m: int, tau: float, camera: Camera | Sequence[Camera] | None, track: bool,
                only: torch.Tensor | None = None) -> Decoded:
        """The training decode: the active anchors (of ``only``, and that may reach ``camera``)
        faded in at frame f, their inputs gathered from the tables (with ``track``, as sparse
        leaves for the optimizer), the decoder, then :meth:`_drawn`."""
        mask = self.active_anchors(f)
        if only is not None:
            mask &= only
        if camera is not None and self.cfg.frustum_cull:
            mask = self.visible_anchors(f, [camera] if isinstance(camera, Camera) else list(camera), mask)
        active = mask.nonzero().squeeze(1)
        shown, dist = self.faded_in(f, active)  # anchors faded out at this frame cannot show: skip them
        if shown is not None:
            active = active.index_select(0, shown)
        sparse: list[SparseLeaf] = []

        def rows_of(name: str, rows: torch.Tensor) -> torch.Tensor:
            full = getattr(self, name)
            if not track:
                return full.index_select(0, rows)
            leaf = full.index_select(0, rows).detach().requires_grad_(True)
            sparse.append(SparseLeaf(name, rows, leaf))
            return leaf

        mu = self.anchor_mu.index_select(0, active)
        fa = rows_of("anchor_feature", active)
        log_scale = rows_of("anchor_log_scale", active)
        xn = self.normalized_positions(mu)
        inside = ((xn >= 0) & (xn <= 1)).all(1, keepdim=True).to(mu.dtype)
        if self.cfg.use_spatial_grid:
            fs, g = self.spatial.query(xn, track)
            if g is not None:
                sparse.append(SparseLeaf("spatial", g.rows, g.leaf))
            fa = fa + fs
        h, g = self.hash.query(xn, tau, m - self.first_segment, track)
        if g is not None:
            sparse.append(SparseLeaf("hash", g.rows, g.leaf))
        seg = torch.tensor([m - self.first_segment], device=mu.device)
        w1, b1, w2, b2 = (rows_of(n, seg)[0] for n in TEMPORAL_MLP)
        ft = torch.relu((h * inside) @ w1 + b1) @ w2 + b2
        fw = torch.cat([fa, ft], dim=1)
        raw, gaussians, keep, shift = self._drawn(f, active, dist, self.decoder(fw, mu, log_scale), rows_of)
        self.reach.record(active, gaussian_reach(raw.means.detach(), raw.scales.detach(), mu))
        q = self.cfg.gaussians_per_anchor
        anchor_ids = active[:, None].expand(-1, q).reshape(-1)
        slot_ids = torch.arange(q, device=active.device).repeat(active.numel())
        shift = None if shift is None else shift.reshape(-1, 3)  # a copy: only training needs it
        if keep is not None:
            anchor_ids, slot_ids = anchor_ids.index_select(0, keep), slot_ids.index_select(0, keep)
            shift = None if shift is None else shift.index_select(0, keep)
        return Decoded(gaussians, anchor_ids, slot_ids, active, raw, m, sparse, shift)

    def _decode_cached(self, f: int, m: int, tau: float) -> Gaussians:
        """The inference decode: every anchor of frame f's window that is faded in, its inputs and
        the heads' outputs from the cache (atgs.model.fast_decode), then :meth:`_drawn`."""
        cache = self.inference_cache
        tables = DecodeTables(self.anchor_mu, self.anchor_keyframe, self.anchor_feature, self.anchor_log_scale,
                              self.bbox_min, self.bbox_max, self.normalized_positions,
                              self.spatial if self.cfg.use_spatial_grid else None, self.hash,
                              (self.tmlp_w1, self.tmlp_b1, self.tmlp_w2, self.tmlp_b2), self.decoder,
                              self.cfg.gaussians_per_anchor)
        window = (self.timeline.window_of_frame(f), bool(self.cfg.static_keyframe0), self.cfg.anchor_layout)
        with cache.lock, torch.no_grad():
            win = cache.window(tables, window, lambda: self.active_anchors(f).nonzero().squeeze(1))
            shown, dist = self.faded_in(f, win.active)
            active, raw = cache.gather(tables, win, shown, m - self.first_segment, tau)
            _, gaussians, _, _ = self._drawn(f, active, dist, raw,
                                             lambda name, rows: getattr(self, name).index_select(0, rows))
            return gaussians

    def _drawn(self, f: int, active: torch.Tensor, dist: torch.Tensor | None, raw: DecodedGaussians,
               rows_of: Callable[[str, torch.Tensor], torch.Tensor]
               ) -> tuple[DecodedGaussians, Gaussians, torch.Tensor | None, torch.Tensor | None]:
        """The steps after the decoder heads, the same for both decodes: the 3D smoothing filter,
        the temporal fade and the velocity shift (atgs.model.anchor_motion), the kept-Gaussians
        cut. ``raw``: the heads' Gaussians of anchors ``active`` at frame f (``dist``: their
        keyframe distances if known); ``rows_of(table, ids)``: rows of a motion table (a tracked
        leaf in training). Returns (``raw`` smoothed, which keeps the unfaded values for the
        densify statistics; the drawn Gaussians; their indices among all A x q, None: all; the
        velocity shift (A, q, 3) of all A x q, None without one). The order of the operations is
        part of training's numerics (autograd sums gradients in it): keep it when adding a step."""
        var = self.smoothing_variance()
        if var is not None:
            scales, opacities = smooth(raw.scales, raw.opacities, var.index_select(0, active))
            raw = replace(raw, scales=scales, opacities=opacities)
        means, opac, shift = raw.means, raw.opacities, None
        if self.has_motion:
            fade = rows_of("anchor_fade", active) if self.cfg.temporal_fade else None
            d, w = self.fade_of(f, active, fade, distances=dist)
            velocity = rows_of("anchor_velocity", active) if self.cfg.anchor_velocity else None
            means, opac, shift = faded_and_moved(means, opac, w, velocity, d)
        opac = opac.reshape(-1)
        keep = self.kept_gaussians(means.detach().reshape(-1, 3), opac.detach())
        parts = [means.reshape(-1, 3), raw.quats.reshape(-1, 4), raw.scales.reshape(-1, 3), opac,
                 raw.colors.reshape(-1, 3)]
        if keep is not None:
            # index_select, not p[keep]: forward and backward (index_add_ instead of an
            # accumulating index_put_) take half the time on the CPU
            parts = [p.index_select(0, keep) for p in parts]
        return raw, Gaussians(*parts), keep, shift

    def kept_gaussians(self, means: torch.Tensor, opacities: torch.Tensor) -> torch.Tensor | None:
        """Indices of the decoded Gaussians that are drawn (None: all of them): above the opacity
        threshold and outside the training cameras' clearance (both decodes cut with it, in :meth:`_drawn`)."""
        mask = None
        if self.cfg.opacity_threshold > 0:
            mask = opacities > self.cfg.opacity_threshold
        if self.clearance.active:
            outside = self.clearance.outside(means)
            mask = outside if mask is None else mask & outside
        return None if mask is None else mask.nonzero().squeeze(1)

    # --- anchor set edits (growing / pruning) ------------------------------------------------------
    def add_anchors(self, mu: torch.Tensor, feature: torch.Tensor, log_scale: torch.Tensor,
                    keyframe: torch.Tensor, velocity: torch.Tensor | None = None,
                    fade: torch.Tensor | None = None) -> None:
        """Append anchors; ``velocity`` (n, 3) defaults to 0, ``fade`` (n, 1) to the initial fade."""
        n, dev = mu.shape[0], self.anchor_mu.device
        if velocity is None:
            velocity = torch.zeros(n, 3, device=dev)
        if fade is None:
            fade = torch.full((n, 1), self.initial_fade(), device=dev)
        self.anchor_mu = torch.cat([self.anchor_mu, mu.float()])
        self.anchor_feature = torch.cat([self.anchor_feature, feature.float()])
        self.anchor_log_scale = torch.cat([self.anchor_log_scale, log_scale.float()])
        self.anchor_keyframe = torch.cat([self.anchor_keyframe, keyframe.long()])
        self.anchor_velocity = torch.cat([self.anchor_velocity, velocity.float()])
        self.anchor_fade = torch.cat([self.anchor_fade, fade.float()])
        self.reach.append(n)

    def keep_anchors(self, keep: torch.Tensor) -> None:
        for name in ("anchor_mu", "anchor_keyframe") + ANCHOR_TABLES:
            setattr(self, name, getattr(self, name)[keep].contiguous())
        self.reach.keep(keep)

    # --- serialization ---------------------------------------------------------------------
    def sparse_tensors(self) -> dict[str, torch.Tensor]:
        return {"anchor_feature": self.anchor_feature, "anchor_log_scale": self.anchor_log_scale,
                "anchor_velocity": self.anchor_velocity, "anchor_fade": self.anchor_fade,
                "spatial": self.spatial.table, "hash": self.hash.table,
                **{n: getattr(self, n) for n in TEMPORAL_MLP}}

    def set_sparse_tensor(self, name: str, value: torch.Tensor) -> None:
        if name == "spatial":
            self.spatial.table = value
        elif name == "hash":
            self.hash.table = value
        else:
            setattr(self, name, value)

    def state_dict(self) -> dict:
        return {
            "anchor_mu": self.anchor_mu, "anchor_keyframe": self.anchor_keyframe,
            **self.sparse_tensors(),
            "bbox_min": self.bbox_min, "bbox_max": self.bbox_max,
            "extent": self.extent, "voxel_size": self.voxel_size, "camera_clearance": self.clearance.radius,
            "near": self.near,
            "num_keyframes": self.timeline.num_keyframes, "num_segments": self.timeline.num_segments,
            "decoder": {k: v.detach().clone() for k, v in self.decoder.state_dict().items()},
        }

    @classmethod
    def from_state(cls, cfg: ModelConfig, state: dict, num_frames: int, fps: float,
                   cameras: list[Camera], segments: range | None = None) -> "ATGSModel":
        """The model of a state dict; ``segments``: the state's per-segment tables hold only
        these segments' rows (a worker of the time partition, see ``__init__``)."""
        tl = Timeline(num_frames, int(state["num_keyframes"]), cfg.window, int(state["num_segments"]))
        a = AnchorInit(state["anchor_mu"], state["anchor_log_scale"], state["anchor_keyframe"],
                       float(state["voxel_size"]))
        if any(n not in state for n in MOTION_TABLES):
            # a checkpoint from before anchor motion: decode it as it was trained
            cfg = replace(cfg, temporal_fade=False, anchor_velocity=False)
        # checkpoints from before the clearance decode as they were trained: without one
        model = cls(cfg, tl, cameras, fps, a, state["bbox_min"], state["bbox_max"], float(state["extent"]),
                    clearance=float(state.get("camera_clearance", 0.0)), segments=segments, draw_hash=False)
        for name, ref in model.sparse_tensors().items():
            if name in MOTION_TABLES and name not in state:
                continue
            value = state[name]
            if name not in ANCHOR_TABLES and value.shape != ref.shape:
                raise ValueError(f"tensor {name!r} has shape {tuple(value.shape)}, config expects {tuple(ref.shape)}")
            model.set_sparse_tensor(name, value.float().contiguous())
        model.decoder.load_state_dict(state["decoder"])
        # checkpoints from before the scaled near plane render as they were trained: at 0.01
        model.near = float(state.get("near", NEAR))
        return model
