"""How much, where and how fast a prepared scene moves, measured from its frames.

:func:`measure_motion` reads a bounded, deterministic sample of the training frames (a few
cameras, at most ``max_frames`` evenly spaced frames each, box-downsampled to at most
``max_side`` pixels) and measures:

- a noise floor: the per-pixel temporal median of consecutive-frame differences, taken at a low
  percentile over pixels (static pixels dominate it even when a large part of the image moves);
  a pixel *changes* between two frames when its channel-mean absolute difference exceeds
  ``threshold = clip(noise_multiplier * noise, min_threshold, max_threshold)``;
- ``moving_fraction``: the fraction of pixels that change at least once (mean over cameras);
- ``energy``: the fraction of pixels that change between consecutive sampled frames, over time
  (where in the sequence the motion happens);
- ``changed_at_lag``: the fraction of pixels that differ between frames ``lag`` apart, averaged
  over the start frames where something moves. It grows with the lag until the moving content
  has turned over (objects left their old place, textures decorrelated) and then saturates;
  ``time_scale`` is its integral time scale (:func:`turnover_time`), in frames. Static scenes
  get ``time_scale = num_frames``;
- the scene extent (bounds, camera spread) and the point spacing that sets the anchor spacing.

Everything is deterministic (no random sampling) and cheap: on the default 12-camera, 120-frame,
256x192 scene it reads 4 x 64 frames (see docs/auto.md for timings).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from atgs.data.errors import DataError
from atgs.data.scene import PreparedScene
from atgs.progress import progress_bar
from atgs.timeline import evenly_spaced


@dataclass(frozen=True)
class MotionConfig:
    """How much of the scene :func:`measure_motion` reads and how it decides what moves."""

    max_cameras: int = 4  # training cameras, evenly spread over the list
    max_frames: int = 64  # evenly spaced frames per camera (first and last always included)
    # box-downsample so that the longer side is at most this: averages out noise and compression
    # artifacts, and keeps the measurement cheap
    max_side: int = 64
    noise_multiplier: float = 6.0  # change threshold in noise floors: ~10 sigma, no false "ever moved"
    # never trust smaller changes: lossy video (H.264 crf 23, 4:2:0) makes static pixels drift by
    # up to ~12/255 over a few seconds (docs/auto.md); lossless data loses only faint changes
    min_threshold: float = 10.0 / 255.0
    max_threshold: float = 0.1  # a noisy/ever-moving estimate must not hide strong changes
    noise_percentile: float = 25.0  # over pixels, of the per-pixel temporal median difference
    active_fraction: float = 1e-3  # a frame pair with fewer changed pixels counts as static
    static_fraction: float = 2e-3  # scenes with fewer ever-moving pixels count as static
    max_spacing_points: int = 4096  # points per keyframe group used for the spacing estimate
    progress: bool = True

    def validate(self) -> None:
        if self.max_cameras < 1:
            raise ValueError(f"max_cameras must be >= 1, got {self.max_cameras}")
        if self.max_frames < 2:
            raise ValueError(f"max_frames must be >= 2, got {self.max_frames}")
        if self.max_side < 8:
            raise ValueError(f"max_side must be >= 8, got {self.max_side}")
        if not 0 < self.min_threshold <= self.max_threshold:
            raise ValueError("need 0 < min_threshold <= max_threshold")


@dataclass
class MotionStats:
    """What :func:`measure_motion` found. Frame counts and lags are in frames of the scene."""

    num_frames: int
    fps: float
    scene_keyframes: int  # keyframes the scene was prepared with (anchors exist only there)
    cameras_used: list[str]
    frames_used: list[int]
    image_size: tuple[int, int]  # (width, height) after downsampling
    noise: float  # estimated noise floor of channel-mean |frame difference|, intensities in [0,1]
    threshold: float  # change threshold used
    moving_fraction: float  # pixels that change at least once (mean over cameras)
    moving_fraction_per_camera: list[float]
    energy: list[float]  # changed-pixel fraction of each consecutive sampled pair
    energy_frames: list[float]  # mid frame of each pair
    lags: list[float]  # frame gaps
    changed_at_lag: list[float]  # changed-pixel fraction between frames `lag` apart
    time_scale: float  # turnover time of the moving content, frames (num_frames when static)
    static: bool
    active_time_fraction: float  # fraction of the sequence (sampled pairs) in which something moves
    bounds_size: list[float]  # (3,) extent of scene.bounds
    extent: float  # longest side of scene.bounds
    points_extent: float  # longest side of the point cloud's bounding box (0 without points)
    camera_spread: float  # largest distance of a camera center from their mean
    point_spacing: float  # median nearest-neighbour spacing within keyframe groups (0 if unknown)
    num_points: int
    points_per_keyframe: float
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)

    @property
    def motion_peak_frame(self) -> float:
        """Mid frame of the pair with the most change (0 for fewer than two frames)."""
        if not self.energy:
            return 0.0
        return float(self.energy_frames[int(np.argmax(self.energy))])

    def energy_by_part(self, parts: int = 4) -> list[float]:
        """Share of the total change energy in each of ``parts`` equal stretches of the sequence."""
        out = np.zeros(parts)
        if not self.energy or self.num_frames < 2:
            return out.tolist()
        for e, f in zip(self.energy, self.energy_frames):
            out[min(parts - 1, int(parts * f / (self.num_frames - 1)))] += e
        s = out.sum()
        return (out / s).tolist() if s > 0 else out.tolist()

    def to_dict(self) -> dict:
        return asdict(self)


# --- pieces (pure functions, tested on their own) -----------------------------------------------

def box_downsample(img: np.ndarray, max_side: int) -> np.ndarray:
    """(H,W,C) uint8 -> channel-first (C,h,w) float32 in [0,1], averaged over s x s blocks so that
    max(H,W)/s <= max_side (channel-first keeps the per-pixel channel sums vectorized)."""
    h, w = img.shape[:2]
    s = max(1, math.ceil(max(h, w) / max_side))
    hh, ww = (h // s) * s, (w // s) * s
    # integer block sums (exact, and cheaper than converting every pixel to float first)
    acc = np.zeros((hh // s, ww // s, img.shape[2]), np.uint32)
    for dy in range(s):
        for dx in range(s):
            acc += img[dy:hh:s, dx:ww:s]
    return np.ascontiguousarray(acc.transpose(2, 0, 1), dtype=np.float32) / np.float32(255.0 * s * s)


def frame_difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Channel-mean absolute difference of channel-first images (..., C, H, W) -> (..., H, W)."""
    d = np.abs(a - b)
    out = d[..., 0, :, :].copy()
    for c in range(1, d.shape[-3]):
        out += d[..., c, :, :]
    return out / np.float32(d.shape[-3])


def estimate_noise(diffs: np.ndarray, percentile: float) -> float:
    """Noise floor from consecutive differences (C, P, H, W): the per-pixel median over time (a
    pixel that moves less than half the time keeps its noise level), at a low percentile over
    pixels (static pixels are the quiet ones)."""
    if diffs.size == 0:
        return 0.0
    per_pixel = np.median(diffs, axis=1)
    return float(np.percentile(per_pixel, percentile))


def turnover_time(lags: np.ndarray, values: np.ndarray) -> float:
    """Integral time scale of a saturating curve: the area above its running maximum,
    ``integral_0^Lmax (1 - env(L) / max) dL`` with env(0) = 0 and linear interpolation. It is
    tau for ``1 - exp(-L/tau)`` and T/2 for a line reaching its plateau at T; the running
    maximum ignores dips of periodic motion. Returns inf when the curve is all zero."""
    lags = np.asarray(lags, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    if len(values) == 0 or values.max() <= 0:
        return math.inf
    env = np.maximum.accumulate(values)
    r = np.concatenate([[1.0], 1.0 - env / env[-1]])
    x = np.concatenate([[0.0], lags])
    return float(np.sum(0.5 * (r[1:] + r[:-1]) * np.diff(x)))


def lag_steps(n: int) -> list[int]:
    """Lags (in sampled steps) 1, 2, 3, 4, 6, 8, 11, 16, ... up to n-1: about 2 per octave."""
    out: list[int] = []
    x = 1.0
    while int(round(x)) <= n - 1:
        v = int(round(x))
        if not out or v > out[-1]:
            out.append(v)
        x *= math.sqrt(2.0)
    return out


def point_spacing(points: np.ndarray, point_keyframes: np.ndarray, max_points: int) -> float:
    """Median over keyframe groups of the median nearest-neighbour distance (duplicates removed),
    the spacing the model's automatic anchor voxel size also uses. Deterministic subsample."""
    from scipy.spatial import cKDTree

    vals = []
    for k in np.unique(point_keyframes):
        p = np.unique(points[point_keyframes == k].astype(np.float64), axis=0)
        if len(p) < 2:
            continue
        q = p[evenly_spaced(len(p), max_points)]
        d, _ = cKDTree(p).query(q, k=2)
        vals.append(float(np.median(d[:, 1])))
    return float(np.median(vals)) if vals else 0.0


# --- the measurement ------------------------------------------------------------------------------

def _load_frames(scene: PreparedScene, cams: list[int], frames: list[int], cfg: MotionConfig) -> np.ndarray:
    """(C, P, 3, h, w) float32 downsampled frames."""
    out = None
    with progress_bar(len(cams) * len(frames), "measure motion", unit="img", enabled=cfg.progress) as bar:
        for ci, cam in enumerate(cams):
            for pi, f in enumerate(frames):
                img = box_downsample(scene.image_uint8(cam, f), cfg.max_side)
                if out is None:
                    out = np.empty((len(cams), len(frames)) + img.shape, np.float32)
                if img.shape != out.shape[2:]:
                    raise DataError(f"{scene.image_path(cam, f)}: camera sizes differ; motion is measured "
                                    "on cameras of one size (pass fewer cameras)")
                out[ci, pi] = img
                bar.update(1)
    assert out is not None
    return out


def _choose_cameras(scene: PreparedScene, max_cameras: int) -> list[int]:
    train = scene.train_indices or list(range(len(scene.cameras)))
    # one size only (the first camera's): frames are stacked
    size = (scene.cameras[train[0]].width, scene.cameras[train[0]].height)
    same = [i for i in train if (scene.cameras[i].width, scene.cameras[i].height) == size]
    return [same[i] for i in evenly_spaced(len(same), max_cameras)]


def measure_motion(scene: PreparedScene, cfg: MotionConfig = MotionConfig()) -> MotionStats:
    """Measure the motion, extent and point spacing of ``scene`` (see the module docstring)."""
    cfg.validate()
    t0 = time.perf_counter()
    F = int(scene.num_frames)
    cams = _choose_cameras(scene, cfg.max_cameras)
    frames = evenly_spaced(F, cfg.max_frames)
    imgs = _load_frames(scene, cams, frames, cfg)
    C, P, _, h, w = imgs.shape
    fr = np.asarray(frames, dtype=np.float64)
    notes: list[str] = []

    if P >= 2:
        diffs = frame_difference(imgs[:, 1:], imgs[:, :-1])  # (C, P-1, h, w)
        noise = estimate_noise(diffs, cfg.noise_percentile)
        thr = threshold = float(np.clip(cfg.noise_multiplier * noise, cfg.min_threshold, cfg.max_threshold))
        changed = diffs > thr
        del diffs
        energy_cp = changed.mean(axis=(2, 3))  # (C, P-1)
        energy = energy_cp.mean(axis=0)
        ever = changed.any(axis=1).mean(axis=(1, 2))  # (C,)
        # a pair is active when it changes clearly more than noise blips, relative to the peak
        active_pair = energy_cp >= max(cfg.active_fraction, 0.05 * float(energy_cp.max()))
        cum = np.concatenate([np.zeros((C, 1), np.int64), np.cumsum(active_pair, axis=1)], axis=1)
        lag_frames, lag_vals = [], []
        for L in lag_steps(P):
            # start i counts when something moves between i and i+L (any active pair in [i, i+L)):
            # static stretches must not dilute the turnover of motion that happens elsewhere
            starts = (cum[:, L:P] - cum[:, 0:P - L]) > 0
            if not starts.any():
                continue
            d = frame_difference(imgs[:, L:], imgs[:, :-L]) > thr  # (C, P-L, h, w)
            frac = d.mean(axis=(2, 3))
            lag_vals.append(float(frac[starts].mean()))
            # mean frame gap of this sampled lag (frames are evenly spaced up to rounding)
            lag_frames.append(float(np.mean(fr[L:] - fr[:-L])))
        moving = float(ever.mean())
        static = moving < cfg.static_fraction or not lag_vals
        tau = math.inf if static else turnover_time(np.asarray(lag_frames), np.asarray(lag_vals))
        time_scale = float(F) if not math.isfinite(tau) else float(min(max(tau, 1.0), F))
        active_time = float(active_pair.any(axis=0).mean())
        energy_frames = (0.5 * (fr[1:] + fr[:-1])).tolist()
    else:
        noise, threshold, moving, static = 0.0, cfg.min_threshold, 0.0, True
        ever = np.zeros(C)
        energy, energy_frames, lag_frames, lag_vals = np.zeros(0), [], [], []
        time_scale, active_time = float(F), 0.0
        notes.append("a single frame: nothing can move")
    if not static and threshold >= cfg.max_threshold:
        notes.append(f"noise is high (or most pixels move all the time): change threshold capped at "
                     f"{cfg.max_threshold * 255:.0f}/255")

    b = np.asarray(scene.bounds, dtype=np.float64)
    bsize = b[1] - b[0]
    pts, _, point_kfs = scene.point_cloud.whole()  # (one read of the file: the points and their keyframes)
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    pext = float((pts.max(0) - pts.min(0)).max()) if len(pts) else 0.0
    centers = np.array([c.center for c in scene.cameras])
    spread = float(np.linalg.norm(centers - centers.mean(0), axis=1).max()) if len(centers) > 1 else 0.0
    spacing = point_spacing(pts, point_kfs, cfg.max_spacing_points) if len(pts) else 0.0
    # keyframes with points: the geometry keyframes, or the denser motion keyframes where the moving content has points
    nkf = max(len(scene.keyframes), len(scene.motion_keyframes))
    return MotionStats(
        num_frames=F, fps=float(scene.fps), scene_keyframes=nkf,
        cameras_used=[scene.cameras[i].name for i in cams], frames_used=[int(f) for f in frames],
        image_size=(int(w), int(h)), noise=float(noise), threshold=float(threshold),
        moving_fraction=moving, moving_fraction_per_camera=[float(x) for x in ever],
        energy=[float(x) for x in energy], energy_frames=[float(x) for x in energy_frames],
        lags=[float(x) for x in lag_frames], changed_at_lag=[float(x) for x in lag_vals],
        time_scale=time_scale, static=bool(static), active_time_fraction=active_time,
        bounds_size=[float(x) for x in bsize], extent=float(bsize.max()), points_extent=pext,
        camera_spread=spread, point_spacing=spacing, num_points=int(len(pts)),
        points_per_keyframe=float(len(pts)) / max(1, len(np.unique(point_kfs))),
        seconds=time.perf_counter() - t0, notes=notes,
    )


def format_stats(s: MotionStats) -> str:
    """A few human-readable lines summarizing the measurement."""
    parts = " ".join(f"{100 * x:.0f}%" for x in s.energy_by_part(4))
    lines = [
        f"measured {len(s.cameras_used)} cameras x {len(s.frames_used)} of {s.num_frames} frames at "
        f"{s.image_size[0]}x{s.image_size[1]} in {s.seconds:.1f} s",
        f"  noise floor {s.noise * 255:.2f}/255, change threshold {s.threshold * 255:.1f}/255",
        f"  moving pixels {100 * s.moving_fraction:.1f}% (ever changing), "
        + ("static scene" if s.static else
           f"turnover time {s.time_scale:.1f} frames, motion in {100 * s.active_time_fraction:.0f}% of the "
           f"sequence, peak near frame {s.motion_peak_frame:.0f}, energy by quarter: {parts}"),
        f"  extent {s.extent:.2f} (bounds), cameras within {s.camera_spread:.2f} of their center, "
        f"{s.num_points} points, spacing {s.point_spacing:.4f}",
    ]
    lines += [f"  note: {n}" for n in s.notes]
    return "\n".join(lines)
