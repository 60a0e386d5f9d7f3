"""Prepared scene: the on-disk layout written by ``atgs-prepare`` and its lazy reader.

Layout (contract, see docs/ARCHITECTURE.md and docs/data.md)::

    DIR/
      scene.json   {"format": "atgs-scene", "version": 1, "name", "fps", "num_frames",
                    "cameras": [Camera.to_dict(), ...]  (undistorted: dist is null),
                    "test_cameras": [names], "keyframes": [frame indices, ascending],
                    "bounds": {"min": [x,y,z], "max": [x,y,z]}, "source": {...}}
      images/<camera name>/<frame:06d>.png  (or .jpg)   frame 0 .. num_frames-1
      masks/<camera name>/<frame:06d>.png   optional, for the cameras scene.json "masks" lists
                   (a list of camera names; ``true`` in older scenes: every camera): foreground
                   masks of every frame, uint8 greyscale, 255 = foreground, the size of the frames
      points.ply   x y z red green blue keyframe   (keyframe = index into "keyframes")
      motion_points.ply   optional, same columns: points on moving content only, keyframe =
                   index into scene.json's "motion_keyframes" (atgs.data.moving_points)

Frames are never held in memory: :meth:`PreparedScene.image` decodes one file per call.
:class:`MemoryScene` is the same interface over frames held in memory (tests, benchmarks).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from PIL import Image

from atgs.cameras import Camera
from atgs.data.errors import DataError
from atgs.data.point_cloud import PlyPointCloud
from atgs.io.atomic import atomic_dir
from atgs.io.images import read_rgb8
from atgs.keyframe_cloud import ArrayPointCloud, PointCloud
from atgs.progress import progress_bar

SCENE_FORMAT = "atgs-scene"
SCENE_VERSION = 1
IMAGE_EXTS = (".png", ".jpg")


def frame_path(root: Path, camera_name: str, frame: int, ext: str = ".png") -> Path:
    return Path(root) / "images" / camera_name / f"{frame:06d}{ext}"


def mask_path(root: Path, camera_name: str, frame: int) -> Path:
    return Path(root) / "masks" / camera_name / f"{frame:06d}.png"


@dataclass
class PreparedScene:
    """A prepared multi-view video scene (read-only view of a directory)."""

    root: Path
    name: str
    fps: float
    num_frames: int
    cameras: list[Camera]
    test_cameras: list[str]
    keyframes: list[int]
    bounds: np.ndarray  # (2,3) float64: row 0 = min corner, row 1 = max corner
    # points.ply, read one keyframe at a time (atgs.data.point_cloud); ``points`` & co. read it whole
    point_cloud: PointCloud
    source: dict = field(default_factory=dict)
    image_ext: str = ".png"
    # points on moving content at more keyframes than ``keyframes`` (empty: none, or a static scene)
    motion_keyframes: list[int] = field(default_factory=list)
    motion_cloud: PointCloud = field(default_factory=lambda: ArrayPointCloud(np.zeros((0, 3)), np.zeros(0), 0))
    # cameras with masks/<camera>/<frame>.png (foreground masks from the source), in camera order
    mask_cameras: list[str] = field(default_factory=list)
    # per keyframe, how many of its points came from each step of atgs-prepare (scene.json)
    point_counts: dict = field(default_factory=dict)
    coverage: dict = field(default_factory=dict)  # atgs-prepare's coverage report (scene.json)

    # --- loading ------------------------------------------------------------------------
    @classmethod
    def load(cls, root: str | Path) -> "PreparedScene":
        root = Path(root)
        meta_path = root / "scene.json"
        if not meta_path.is_file():
            raise DataError(f"{meta_path}: not found; is {root} a directory written by atgs-prepare?")
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, ValueError) as e:
            raise DataError(f"{meta_path}: unreadable JSON ({e}); re-run atgs-prepare") from None
        if meta.get("format") != SCENE_FORMAT:
            raise DataError(f"{meta_path}: 'format' is {meta.get('format')!r}, expected {SCENE_FORMAT!r}")
        if meta.get("version") != SCENE_VERSION:
            raise DataError(f"{meta_path}: unsupported version {meta.get('version')!r} (this reader knows {SCENE_VERSION})")
        try:
            cameras = [Camera.from_dict(c) for c in meta["cameras"]]
            num_frames = int(meta["num_frames"])
            fps = float(meta["fps"])
            keyframes = [int(k) for k in meta.get("keyframes", [0])]
            test_cameras = [str(n) for n in meta.get("test_cameras", [])]
            b = meta["bounds"]
            bounds = np.array([b["min"], b["max"]], dtype=np.float64).reshape(2, 3)
        except (KeyError, TypeError, ValueError) as e:
            raise DataError(f"{meta_path}: missing or malformed field ({e}); re-run atgs-prepare") from None
        names = [c.name for c in cameras]
        if not cameras or num_frames < 1:
            raise DataError(f"{meta_path}: no cameras or no frames")
        if len(set(names)) != len(names):
            raise DataError(f"{meta_path}: duplicate camera names")
        unknown = [n for n in test_cameras if n not in names]
        if unknown:
            raise DataError(f"{meta_path}: test camera(s) {unknown} are not in 'cameras'")
        if sorted(set(keyframes)) != keyframes or not keyframes or keyframes[0] < 0 or keyframes[-1] >= num_frames:
            raise DataError(f"{meta_path}: 'keyframes' must be ascending unique frame indices in [0, {num_frames})")
        cam_dir = root / "images" / names[0]
        ext = next((e for e in IMAGE_EXTS if frame_path(root, names[0], 0, e).is_file()), None)
        if ext is None:
            raise DataError(f"{frame_path(root, names[0], 0)}: first frame of camera {names[0]} not found in {cam_dir}")
        cloud = PlyPointCloud.open(root / "points.ply", len(keyframes))
        mkfs, motion = _read_motion_points(root, meta, meta_path, num_frames)
        mask_cams = _read_mask_cameras(meta.get("masks"), names, meta_path)
        lost = next((n for n in mask_cams if not mask_path(root, n, 0).is_file()), None)
        if lost is not None:
            raise DataError(f"{mask_path(root, lost, 0)}: not found but scene.json says camera {lost} has masks; "
                            "re-run atgs-prepare")
        return cls(
            root=root, name=str(meta.get("name", root.name)), fps=fps, num_frames=num_frames,
            cameras=cameras, test_cameras=test_cameras, keyframes=keyframes, bounds=bounds,
            point_cloud=cloud, source=dict(meta.get("source", {})),
            image_ext=ext, motion_keyframes=mkfs, motion_cloud=motion, mask_cameras=mask_cams,
            point_counts=dict(meta.get("keyframe_points") or {}), coverage=dict(meta.get("coverage") or {}),
        )

    # --- the points, whole (what training reads, it reads per keyframe: point_cloud) ---------
    @property
    def points(self) -> np.ndarray:
        """(P, 3) float32, in keyframe order (read from the file at each use)."""
        return self.point_cloud.whole()[0]

    @property
    def point_colors(self) -> np.ndarray:
        """(P, 3) float32 in [0, 1]."""
        return self.point_cloud.whole()[1]

    @property
    def point_keyframes(self) -> np.ndarray:
        """(P,) int64, index into ``keyframes``."""
        return self.point_cloud.whole()[2]

    @property
    def motion_points(self) -> np.ndarray:
        return self.motion_cloud.whole()[0]

    @property
    def motion_point_keyframes(self) -> np.ndarray:
        return self.motion_cloud.whole()[2]

    @property
    def measured_counts(self) -> list[int] | None:
        """Per keyframe, how many of its first points SIFT or stereo measured, not filled in
        (keyframe_points writes each keyframe's measured points first, then its fill and
        extension; ``point_counts`` says how many). None (all measured) where the counts are
        missing or disagree with points.ply: treating a fill point as measured only ever makes
        less space look empty (atgs.geometry.free_space)."""
        return _measured_counts(self.point_counts, self.point_cloud)

    @property
    def measured_points(self) -> np.ndarray:
        """(P,) bool over ``points``: the measured points (``measured_counts``)."""
        return self.point_cloud.measured_mask(self.measured_counts)

    # --- camera splits ------------------------------------------------------------------
    @property
    def camera_names(self) -> list[str]:
        return [c.name for c in self.cameras]

    @property
    def test_indices(self) -> list[int]:
        test = set(self.test_cameras)
        return [i for i, c in enumerate(self.cameras) if c.name in test]

    @property
    def train_indices(self) -> list[int]:
        test = set(self.test_cameras)
        return [i for i, c in enumerate(self.cameras) if c.name not in test]

    # --- foreground masks ------------------------------------------------------------------
    @property
    def has_masks(self) -> bool:
        """Some camera has masks (``mask_cameras``)."""
        return bool(self.mask_cameras)

    def has_mask(self, cam_index: int) -> bool:
        return self.cameras[cam_index].name in self.mask_cameras

    # --- frames -------------------------------------------------------------------------
    def _check_index(self, cam_index: int, frame: int) -> str:
        """The camera's name, after checking both indices."""
        if not 0 <= cam_index < len(self.cameras):
            raise IndexError(f"camera index {cam_index} out of range [0, {len(self.cameras)})")
        if not 0 <= frame < self.num_frames:
            raise IndexError(f"frame {frame} out of range [0, {self.num_frames})")
        return self.cameras[cam_index].name

    def image_path(self, cam_index: int, frame: int) -> Path:
        return frame_path(self.root, self._check_index(cam_index, frame), frame, self.image_ext)

    def image(self, cam_index: int, frame: int) -> np.ndarray:
        """Frame ``frame`` of camera ``cam_index`` as (H,W,3) float32 in [0,1], read from disk now."""
        return self.image_uint8(cam_index, frame).astype(np.float32) / 255.0

    def image_uint8(self, cam_index: int, frame: int) -> np.ndarray:
        path = self.image_path(cam_index, frame)
        try:
            arr = read_rgb(path)
        except FileNotFoundError:
            raise DataError(f"{path}: frame file missing; re-run atgs-prepare") from None
        except OSError as e:
            raise DataError(f"{path}: unreadable image ({e}); re-run atgs-prepare") from None
        return self._check_size(path, arr, cam_index)

    def mask(self, cam_index: int, frame: int) -> np.ndarray:
        """Foreground mask of frame ``frame`` of camera ``cam_index``, (H,W) bool, read from disk now."""
        name = self._check_index(cam_index, frame)
        if not self.has_masks:
            raise DataError(f"{self.root / 'scene.json'}: the scene has no masks (its source had none)")
        if name not in self.mask_cameras:
            raise DataError(f"{self.root / 'scene.json'}: camera {name} has no masks (its source had none for it; "
                            f"cameras with masks: {', '.join(self.mask_cameras)})")
        path = mask_path(self.root, name, frame)
        return self._check_size(path, read_mask(path), cam_index)

    def _check_size(self, path: Path, arr: np.ndarray, cam_index: int) -> np.ndarray:
        cam = self.cameras[cam_index]
        if arr.shape[:2] != (cam.height, cam.width):
            raise DataError(f"{path}: size {arr.shape[1]}x{arr.shape[0]} differs from camera {cam.name} ({cam.width}x{cam.height})")
        return arr


@dataclass
class MemoryScene:
    """A scene held in memory, with what training and evaluation read of a
    :class:`PreparedScene` (cameras, frames, keyframe points, test cameras by name): toy scenes
    of the tests and the benchmarks' synthetic scenes, and what :func:`write_prepared_scene` and
    :func:`write_scene_metadata` write. ``frames[(camera index, frame)]`` is a uint8 (H, W, 3)
    image; a writer may take the frames from elsewhere and leave it empty."""

    cameras: list[Camera]
    num_frames: int
    fps: float = 30.0
    keyframes: list[int] = field(default_factory=lambda: [0])
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    point_keyframes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # index into keyframes
    test_cameras: list[str] = field(default_factory=list)
    frames: dict[tuple[int, int], np.ndarray] = field(default_factory=dict)
    bounds: np.ndarray | None = None  # (2, 3) min and max corner, as PreparedScene.bounds (None: from the points)
    motion_keyframes: list[int] = field(default_factory=list)  # as PreparedScene's
    motion_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    motion_point_keyframes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    point_colors: np.ndarray | None = None  # (P, 3) in [0, 1]; None: grey (what a writer stores)
    motion_point_colors: np.ndarray | None = None  # likewise for the motion points

    @property
    def measured_points(self) -> np.ndarray:
        """(P,) bool, as PreparedScene's: all True, nothing here was filled in."""
        return np.ones(len(self.points), bool)

    @property
    def measured_counts(self) -> None:
        """As PreparedScene's: all measured."""
        return None

    @property
    def point_cloud(self) -> PointCloud:
        """``points`` by keyframe, as PreparedScene's."""
        return ArrayPointCloud(self.points, self.point_keyframes, len(self.keyframes), self.point_colors)

    @property
    def motion_cloud(self) -> PointCloud:
        return ArrayPointCloud(self.motion_points, self.motion_point_keyframes, len(self.motion_keyframes),
                               self.motion_point_colors)

    @property
    def train_indices(self) -> list[int]:
        return [i for i, c in enumerate(self.cameras) if c.name not in self.test_cameras]

    @property
    def test_indices(self) -> list[int]:
        return [i for i, c in enumerate(self.cameras) if c.name in self.test_cameras]

    def image_uint8(self, cam_index: int, frame: int) -> np.ndarray:
        return self.frames[(cam_index, frame)]

    def image(self, cam_index: int, frame: int) -> np.ndarray:
        return self.image_uint8(cam_index, frame).astype(np.float32) / 255.0


def read_rgb(path: Path) -> np.ndarray:
    """(H,W,3) uint8 of an image file (any mode: atgs.io.images.to_rgb8)."""
    return read_rgb8(path)


def read_mask(path: Path) -> np.ndarray:
    """(H,W) bool foreground of a mask image of any mode: white (128 or more in any channel) is
    foreground; a mask coded 0/1 (nothing above 1, as some datasets store them) has 1 as foreground."""
    try:
        v = read_rgb8(path).max(axis=2)
    except FileNotFoundError:
        raise DataError(f"{path}: mask not found") from None
    except OSError as e:
        raise DataError(f"{path}: unreadable mask ({e})") from None
    return v >= (1 if v.max() <= 1 else 128)


def save_mask(root: Path, cam: Camera, frame: int, mask: np.ndarray) -> None:
    """Write one foreground mask of a prepared scene: greyscale PNG, 255 = foreground."""
    if mask.shape != (cam.height, cam.width):
        raise ValueError(f"mask {frame} of {cam.name}: shape {mask.shape} != ({cam.height},{cam.width})")
    Image.fromarray(np.where(mask, 255, 0).astype(np.uint8)).save(mask_path(root, cam.name, frame), compress_level=1)


def resize_frame(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """A uint8 (H,W,3) frame at ``width`` x ``height`` (Lanczos): how training and evaluation see
    the ground truth at a reduced ``resolution_scale``. Returned as is when the size matches."""
    if img.shape[:2] == (height, width):
        return img
    return np.asarray(Image.fromarray(img).resize((width, height), Image.Resampling.LANCZOS))


def _read_motion_points(root: Path, meta: dict, meta_path: Path, num_frames: int
                        ) -> tuple[list[int], PointCloud]:
    """The optional moving-content points: (motion keyframes, their cloud)."""
    try:
        mkfs = [int(k) for k in meta.get("motion_keyframes", [])]
    except (TypeError, ValueError):
        raise DataError(f"{meta_path}: 'motion_keyframes' must be a list of frame indices; re-run atgs-prepare") from None
    path = root / "motion_points.ply"
    if not mkfs:
        return [], ArrayPointCloud(np.zeros((0, 3)), np.zeros(0), 0)
    if sorted(set(mkfs)) != mkfs or mkfs[0] < 0 or mkfs[-1] >= num_frames:
        raise DataError(f"{meta_path}: 'motion_keyframes' must be ascending unique frame indices in [0, {num_frames})")
    if not path.is_file():
        raise DataError(f"{path}: not found but scene.json lists motion keyframes; re-run atgs-prepare")
    return mkfs, PlyPointCloud.open(path, len(mkfs))


def _read_mask_cameras(value, names: list[str], meta_path: Path) -> list[str]:
    """scene.json "masks": the cameras with masks, in camera order. ``true`` (older scenes) is
    every camera; absent or ``false``, none."""
    if value is None or value is False:
        return []
    if value is True:
        return list(names)
    if not isinstance(value, list) or not all(isinstance(n, str) for n in value):
        raise DataError(f"{meta_path}: 'masks' must be a list of camera names (or true); re-run atgs-prepare")
    unknown = [n for n in value if n not in names]
    if unknown:
        raise DataError(f"{meta_path}: 'masks' names camera {unknown[0]}, which is not in 'cameras'; "
                        "re-run atgs-prepare")
    return [n for n in names if n in value]


def _measured_counts(counts: dict, cloud: PointCloud) -> list[int] | None:
    """PreparedScene.measured_counts of ``counts`` (scene.json's "keyframe_points")."""
    try:
        steps = [[int(x) for x in counts[k]] for k in ("sift", "stereo", "fill", "extend")]
    except (KeyError, TypeError, ValueError):
        return None
    K = cloud.num_keyframes
    if any(len(st) < K or len(st) != len(steps[0]) for st in steps) or \
            any(cloud.count(j) != sum(st[j] for st in steps) for j in range(K)):
        return None
    return [steps[0][j] + steps[1][j] for j in range(K)]


# --- points.ply -----------------------------------------------------------------------------

def write_points_ply(path: Path, points: np.ndarray, colors: np.ndarray, keyframes: np.ndarray) -> None:
    """Binary PLY with x y z (float32), red green blue (uint8), keyframe (int32)."""
    from plyfile import PlyData, PlyElement

    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    colors = np.asarray(colors).reshape(-1, 3)
    # float colors are in [0,1], integer colors in [0,255]
    colors = colors.astype(np.float64) * 255.0 if colors.dtype.kind == "f" else colors.astype(np.float64)
    keyframes = np.asarray(keyframes, dtype=np.int64).reshape(-1)
    if not (len(points) == len(colors) == len(keyframes)):
        raise ValueError("points, colors and keyframes must have the same length")
    v = np.empty(len(points), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"),
                                     ("green", "u1"), ("blue", "u1"), ("keyframe", "i4")])
    v["x"], v["y"], v["z"] = points.T
    c = np.clip(np.round(colors), 0, 255).astype(np.uint8)
    v["red"], v["green"], v["blue"] = c.T
    v["keyframe"] = keyframes
    # each keyframe's rows together, in their given order: readers take a keyframe at a time
    v = v[np.argsort(keyframes, kind="stable")]
    PlyData([PlyElement.describe(v, "vertex")], text=False).write(str(path))


# --- builder (used by atgs-prepare and by tests to make toy scenes) --------------------------

MIN_BOUNDS_POINTS = 100  # fewer points than this say nothing robust about the scene's extent


def compute_bounds(points: np.ndarray, cameras: Sequence[Camera]) -> np.ndarray:
    """Scene bounds, padded by 5% of the longest side: the 1-99 percentile box of the points
    when there are at least MIN_BOUNDS_POINTS of them; else the box of the camera centers and of
    the space in front of the cameras that at least two of them see (a handful of points would
    give an arbitrary box, so they are ignored)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) >= MIN_BOUNDS_POINTS:
        lo, hi = np.percentile(pts, 1, axis=0), np.percentile(pts, 99, axis=0)
    else:
        c = np.array([cam.center for cam in cameras])
        if len(cameras) >= 2:
            from atgs.geometry.seen_space import fallback_points

            c = np.concatenate([c, fallback_points(cameras, 2000)])
        lo, hi = np.percentile(c, 1, axis=0), np.percentile(c, 99, axis=0)
    pad = 0.05 * max(float(np.max(hi - lo)), 1e-6)
    return np.stack([lo - pad, hi + pad])


def write_prepared_scene(
    out: str | Path,
    scene: MemoryScene,
    frames: Callable[[int, int], np.ndarray] | None = None,
    *,
    name: str | None = None,
    source: dict | None = None,
    image_ext: str = ".png",
    overwrite: bool = False,
    progress: bool = False,
) -> Path:
    """Write ``scene`` as a prepared scene, atomically, and return its path.

    ``frames(cam_index, frame)`` (default: the scene's own, ``scene.image_uint8``) returns an
    (H,W,3) image (uint8, or float in [0,1]); it is called once per file so the frames never
    need to be in memory together. The keyframes are stored sorted and without repeats.
    """
    out = Path(out)
    cameras = list(scene.cameras)
    if any(c.dist is not None for c in cameras):
        raise ValueError("prepared scenes hold undistorted cameras (dist must be None)")
    if image_ext not in IMAGE_EXTS:
        raise ValueError(f"image_ext must be one of {IMAGE_EXTS}")
    frames = scene.image_uint8 if frames is None else frames
    colors = None if scene.point_colors is None else np.asarray(scene.point_colors, np.float32).reshape(-1, 3)
    scene = replace(scene, cameras=cameras, keyframes=sorted({int(k) for k in scene.keyframes}), point_colors=colors)
    with atomic_dir(out, overwrite) as tmp:
        total = len(cameras) * scene.num_frames
        with progress_bar(total, "write frames", unit="img", enabled=progress) as bar:
            for ci, cam in enumerate(cameras):
                (tmp / "images" / cam.name).mkdir(parents=True)
                for f in range(scene.num_frames):
                    save_frame(tmp, cam, f, np.asarray(frames(ci, f)), image_ext)
                    bar.update(1)
        write_scene_metadata(tmp, scene, name=name or out.name, source=source)
    return out


def save_frame(root: Path, cam: Camera, frame: int, img: np.ndarray, image_ext: str = ".png") -> None:
    """Write one frame of a prepared scene (uint8, or float in [0,1])."""
    if img.dtype != np.uint8:
        img = np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)
    if img.shape[:2] != (cam.height, cam.width):
        raise ValueError(f"frame {frame} of {cam.name}: shape {img.shape} != ({cam.height},{cam.width},3)")
    opts = {"compress_level": 1} if image_ext == ".png" else {"quality": 95}
    Image.fromarray(img[..., :3]).save(frame_path(root, cam.name, frame, image_ext), **opts)


def write_scene_metadata(root: Path, scene: MemoryScene, *, name: str, source: dict | None = None,
                         extra: dict | None = None, masks: bool | Sequence[str] = False) -> None:
    """Write scene.json and points.ply of ``scene`` (its frames are not read) into ``root``
    (whose images/ already exist), then validate. Motion keyframes add motion_points.ply and
    "motion_keyframes"; ``extra`` adds informational keys (e.g. "coverage") that readers may
    ignore; ``masks`` names the cameras whose every frame has a mask in masks/ (``True``: all of
    them), stored as "masks", the list of their names (the key is absent when none has masks).
    Missing colours are stored grey."""
    root = Path(root)
    cameras = list(scene.cameras)
    mask_cams = _mask_camera_list(masks, [c.name for c in cameras])
    pts = np.asarray(scene.points, np.float32).reshape(-1, 3)
    # (from the training cameras: nothing about a held-out camera shapes what training starts from)
    train = [c for c in cameras if c.name not in set(scene.test_cameras)] or cameras
    bounds = compute_bounds(pts, train) if scene.bounds is None else scene.bounds
    meta = {
        "format": SCENE_FORMAT,
        "version": SCENE_VERSION,
        "name": name,
        "fps": float(scene.fps),
        "num_frames": int(scene.num_frames),
        "cameras": [c.to_dict() for c in cameras],
        "test_cameras": list(scene.test_cameras),
        "keyframes": [int(k) for k in scene.keyframes],
        "bounds": {"min": np.asarray(bounds)[0].tolist(), "max": np.asarray(bounds)[1].tolist()},
        "source": dict(source or {}),
        **(extra or {}),
        **({"masks": mask_cams} if mask_cams else {}),
    }
    if len(scene.motion_keyframes):
        meta["motion_keyframes"] = [int(k) for k in scene.motion_keyframes]
        write_points_ply(root / "motion_points.ply", scene.motion_points,
                         _grey_if_none(scene.motion_point_colors, len(scene.motion_point_keyframes)),
                         scene.motion_point_keyframes)
    write_points_ply(root / "points.ply", pts, _grey_if_none(scene.point_colors, len(pts)),
                     np.asarray(scene.point_keyframes, np.int64))
    (root / "scene.json").write_text(json.dumps(meta, indent=1))
    PreparedScene.load(root)  # validate what we wrote before it becomes visible


def _mask_camera_list(masks: bool | Sequence[str], names: list[str]) -> list[str]:
    """write_scene_metadata's ``masks`` as camera names in camera order."""
    if isinstance(masks, bool):
        return list(names) if masks else []
    unknown = [n for n in masks if n not in names]
    if unknown:
        raise ValueError(f"masks names camera {unknown[0]!r}, which the scene does not have")
    return [n for n in names if n in set(masks)]


def _grey_if_none(colors: np.ndarray | None, n: int) -> np.ndarray:
    """``colors`` as given (float in [0, 1] or integer in [0, 255]: write_points_ply), or n greys."""
    return np.full((n, 3), 0.5, np.float32) if colors is None else colors
