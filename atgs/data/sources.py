"""Input dataset layouts: detection and uniform per-camera frame access.

Supported (``--format``):
- ``n3dv``: ``camXX.mp4`` + ``poses_bounds.npy`` (rows follow the sorted video names);
- ``colmap-frames``: ``frameNNNNNN/images/camXX.png`` + a COLMAP model in ``sparse/0`` (at the
  top level or inside the first frame folder), the 3DGStream / VRU / MeetRoom style;
- ``easyvolcap``: ``intri.yml`` + ``extri.yml`` + ``images/<cam>/<frame>.jpg``;
- ``d3dgs``: Dynamic 3D Gaussians (CMU Panoptic): ``train_meta.json`` + ``test_meta.json`` +
  ``ims/<cam>/<frame>.jpg``, optional foreground masks ``seg/<cam>/<frame>.png`` for any of the
  cameras (the published captures have them for the training cameras only); the cameras of
  ``test_meta.json`` are held out by default; ``init_pt_cld.npz``, when present, only hints the
  cameras' depth ranges (:func:`point_hints`);
- ``videos``: plain ``*.mp4`` (one per static camera) with no poses -> SfM on the first frame;
- ``images``: ``<cam>/<frame>.png`` folders with no poses -> SfM on the first frame.
"""

from __future__ import annotations

import re
import zipfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from PIL import Image

from atgs.cameras import Camera
from atgs.data.camera_formats import (cameras_from_d3dgs, cameras_from_poses_bounds, cameras_from_reconstruction,
                                     read_d3dgs_meta, read_easyvolcap)
from atgs.data.errors import DataError
from atgs.data.pose_check import proper_world
from atgs.data.scene import read_mask
from atgs.data.video import VIDEO_EXTS, iter_frames, video_info
from atgs.geometry.projection import project
from atgs.io.images import read_rgb8

SourceFormat = Literal["auto", "n3dv", "colmap-frames", "easyvolcap", "d3dgs", "videos", "images"]
IMAGE_FILE_EXTS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
_FRAME_DIR = re.compile(r"^frame_?\d+$|^\d+$")


@dataclass
class Source:
    """One camera per entry; frames are decoded lazily, one at a time."""

    kind: str
    root: Path
    camera_names: list[str]
    cameras: list[Camera] | None  # None: poses unknown (SfM needed)
    num_frames: list[int]
    sizes: list[tuple[int, int]]  # (width, height) of the frames as stored
    fps: float
    default_test: list[str]
    videos: list[Path] | None = None  # one video per camera, or
    images: list[list[Path]] | None = None  # per camera, the frame files in order
    extra: dict = field(default_factory=dict)
    # per camera, a foreground mask file per frame, or None for a camera without masks (d3dgs
    # seg/); None: no camera has masks
    masks: list[list[Path] | None] | None = None
    calibration: Path | None = None  # the file the poses came from, named in messages about them
    # the layout's poses are written by hand or by ad-hoc scripts (d3dgs metas, EasyVolcap YAML),
    # where camera-to-world matrices filed as world-to-camera are common (pose_check)
    poses_by_hand: bool = False
    # the mirror that made the file's left-handed world right-handed (pose_check.proper_world)
    world_mirror: np.ndarray | None = None
    # a capture's own initial points (xyz in the cameras' world), only ever depth-range hints
    hint_points: np.ndarray | None = None

    def depth_hints(self, cams: Sequence[Camera]) -> None:
        """(Re)compute ``extra['near_far']`` from ``hint_points`` for ``cams`` (after the poses'
        reading is settled, pose_check)."""
        if self.hint_points is not None:
            self.extra["near_far"] = point_hints(self.hint_points, cams)
            self.extra["init_points"] = len(self.hint_points)

    def file_of(self, ci: int) -> Path:
        return self.videos[ci] if self.videos is not None else self.root / self.camera_names[ci]

    def frames(self, ci: int, indices: Sequence[int]) -> Iterator[tuple[int, np.ndarray]]:
        """Yield (frame index, (H,W,3) uint8) for ascending ``indices``."""
        indices = list(indices)
        if not indices:
            return
        if self.videos is not None:
            wanted = set(indices)
            got = 0
            for i, img in iter_frames(self.videos[ci], indices[0], indices[-1] + 1):
                if i in wanted:
                    got += 1
                    yield i, img
            if got < len(indices):
                raise DataError(f"{self.videos[ci]}: decoded only {got} of the {len(indices)} requested frames "
                                f"(the file is truncated or its header overstates the frame count)")
        else:
            for i in indices:
                yield i, load_image(self.images[ci][i])

    def mask(self, ci: int, i: int) -> np.ndarray:
        """Foreground mask (H,W) bool of frame ``i`` of camera ``ci``; cameras with masks only."""
        if self.masks is None or self.masks[ci] is None:
            raise DataError(f"{self.root}: camera {self.camera_names[ci]} has no masks")
        return read_mask(self.masks[ci][i])

    def camera_has_masks(self, ci: int, frames: Sequence[int]) -> bool:
        """Whether camera ``ci`` has a mask of each of ``frames``. Masks of only some of them is an
        error: the camera's motion masks would switch source from frame to frame."""
        paths = None if self.masks is None else self.masks[ci]
        if paths is None:
            return False
        missing = next((paths[i] for i in frames if not paths[i].is_file()), None)
        if missing is not None:
            raise DataError(f"{missing}: not found, but camera {self.camera_names[ci]} has masks of other frames; "
                            f"add the missing masks, or remove {missing.parent} to prepare the camera without masks")
        return True


def load_image(path: Path) -> np.ndarray:
    try:
        return read_rgb8(path)
    except FileNotFoundError:
        raise DataError(f"{path}: image not found") from None
    except OSError as e:
        raise DataError(f"{path}: unreadable image ({e})") from None


def image_size(path: Path) -> tuple[int, int]:
    try:
        with Image.open(path) as im:
            return im.size
    except FileNotFoundError:
        raise DataError(f"{path}: image not found") from None
    except OSError as e:
        raise DataError(f"{path}: unreadable image ({e})") from None


def _videos_in(root: Path) -> list[Path]:
    return sorted(p for p in root.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_EXTS)


def _images_in(d: Path) -> list[Path]:
    return sorted(p for p in d.iterdir() if p.is_file() and p.suffix in IMAGE_FILE_EXTS)


def _frame_dirs(root: Path) -> list[Path]:
    return sorted(p for p in root.iterdir() if p.is_dir() and _FRAME_DIR.match(p.name) and (p / "images").is_dir())


def _camera_dirs(root: Path) -> list[Path]:
    return sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".") and _images_in(p))


def detect_format(root: Path) -> str:
    root = Path(root)
    if not root.exists():
        raise DataError(f"{root}: source path does not exist")
    if not root.is_dir():
        raise DataError(f"{root}: source must be a directory (of videos, image folders or frame folders)")
    if (root / "train_meta.json").is_file():
        return "d3dgs"
    if (root / "poses_bounds.npy").is_file():
        return "n3dv"
    if (root / "intri.yml").is_file() or (root / "extri.yml").is_file():
        return "easyvolcap"
    if _frame_dirs(root):
        return "colmap-frames"
    if _videos_in(root):
        return "videos"
    if (root / "images").is_dir() and _camera_dirs(root / "images"):
        return "images"
    if _camera_dirs(root):
        return "images"
    if not any(root.iterdir()):
        raise DataError(f"{root}: folder is empty; expected camXX.mp4 videos, <cam>/ image folders, "
                        "frameNNNNNN/images/ folders, intri.yml/extri.yml or train_meta.json")
    raise DataError(f"{root}: cannot recognise the layout; expected camXX.mp4 (+ poses_bounds.npy), "
                    "<cam>/ image folders, frameNNNNNN/images/ + sparse/0, intri.yml/extri.yml + images/, or "
                    "train_meta.json + ims/; or pass --format")


def open_source(root: Path, fmt: SourceFormat = "auto") -> Source:
    root = Path(root)
    kind = detect_format(root) if fmt == "auto" else fmt
    if not root.is_dir():
        raise DataError(f"{root}: source directory not found")
    return {"n3dv": _open_n3dv, "colmap-frames": _open_colmap_frames, "easyvolcap": _open_easyvolcap,
            "d3dgs": _open_d3dgs, "videos": _open_videos, "images": _open_images}[kind](root)


# --- video layouts --------------------------------------------------------------------------

def _video_source(root: Path, kind: str) -> Source:
    vids = _videos_in(root)
    if not vids:
        raise DataError(f"{root}: no videos ({', '.join(VIDEO_EXTS)}) found")
    infos = [video_info(v) for v in vids]
    names = [v.stem for v in vids]
    sizes = [(i[1], i[2]) for i in infos]
    fps = infos[0][3]
    test = ["cam00"] if "cam00" in names else [names[0]]
    return Source(kind, root, names, None, [i[0] for i in infos], sizes, fps, test, videos=vids)


def _open_n3dv(root: Path) -> Source:
    src = _video_source(root, "n3dv")
    pb = root / "poses_bounds.npy"
    try:
        arr = np.load(pb)
    except (OSError, ValueError) as e:
        raise DataError(f"{pb}: unreadable ({e})") from None
    src.cameras, near_far = cameras_from_poses_bounds(arr, src.camera_names, src.sizes, source=str(pb))
    src.calibration = pb
    src.extra["near_far"] = near_far.tolist()
    return src


def _open_videos(root: Path) -> Source:
    return _video_source(root, "videos")


# --- image-folder layouts ---------------------------------------------------------------------

def _image_source(kind: str, root: Path, names: list[str], files: list[list[Path]], cameras: list[Camera] | None,
                  test: list[str]) -> Source:
    if not names:
        raise DataError(f"{root}: no camera image folders found")
    for n, f in zip(names, files):
        if not f:
            raise DataError(f"{root}: camera {n} has no images")
    sizes = []
    for n, f in zip(names, files):
        sizes.append(image_size(f[0]))
    return Source(kind, root, names, cameras, [len(f) for f in files], sizes, 30.0, test, images=files)


def _open_images(root: Path) -> Source:
    base = root / "images" if (root / "images").is_dir() and _camera_dirs(root / "images") else root
    dirs = _camera_dirs(base)
    if not dirs:
        raise DataError(f"{base}: no camera folders with images found")
    names = [d.name for d in dirs]
    return _image_source("images", root, names, [_images_in(d) for d in dirs], None, [names[0]])


def _open_easyvolcap(root: Path) -> Source:
    img_root = root / "images"
    if not img_root.is_dir():
        raise DataError(f"{img_root}: missing (EasyVolcap scenes keep frames in images/<cam>/)")
    dirs = {d.name: d for d in _camera_dirs(img_root)}
    sizes = {n: image_size(_images_in(d)[0]) for n, d in dirs.items()}
    cams = read_easyvolcap(root, sizes)
    missing = [c.name for c in cams if c.name not in dirs]
    if missing:
        raise DataError(f"{img_root / missing[0]}: image folder missing for camera {missing[0]} listed in intri.yml")
    names = [c.name for c in cams]
    src = _image_source("easyvolcap", root, names, [_images_in(dirs[n]) for n in names], cams, [names[0]])
    src.calibration, src.poses_by_hand = root / "extri.yml", True
    return src


def _find_colmap_model(root: Path, first_frame: Path) -> Path:
    for cand in (root / "sparse" / "0", root / "sparse", first_frame / "sparse" / "0", first_frame / "sparse"):
        if (cand / "cameras.bin").is_file() or (cand / "cameras.txt").is_file():
            return cand
    raise DataError(f"{root / 'sparse' / '0'}: COLMAP model not found (also looked in {first_frame / 'sparse' / '0'})")


def _open_colmap_frames(root: Path) -> Source:
    import pycolmap

    frames = _frame_dirs(root)
    if not frames:
        raise DataError(f"{root}: no frameNNNNNN/images/ folders found")
    model = _find_colmap_model(root, frames[0])
    try:
        rec = pycolmap.Reconstruction(str(model))
    except Exception as e:  # noqa: BLE001 - pycolmap raises generic errors for bad models
        raise DataError(f"{model}: unreadable COLMAP model ({str(e).splitlines()[0][:120]})") from None
    cams = cameras_from_reconstruction(rec)
    if not cams:
        raise DataError(f"{model}: the COLMAP model has no posed images")
    first = {p.stem: p for p in _images_in(frames[0] / "images")}
    cams = [c for c in cams if c.name in first]
    if not cams:
        raise DataError(f"{frames[0] / 'images'}: no image matches a COLMAP image name in {model}")
    names = [c.name for c in cams]
    files: list[list[Path]] = []
    for n in names:
        ext = first[n].suffix
        files.append([f / "images" / f"{n}{ext}" for f in frames])
    # a frame folder missing a camera's image makes that camera shorter: count present prefix
    counts = []
    for n, fl in zip(names, files):
        k = next((i for i, p in enumerate(fl) if not p.is_file()), len(fl))
        counts.append(k)
    src = _image_source("colmap-frames", root, names, [fl[:k] for fl, k in zip(files, counts)], cams, [names[0]])
    src.extra["colmap_model"] = str(model)
    src.calibration = model
    src.extra["missing"] = {n: str(fl[k]) for n, fl, k in zip(names, files, counts) if k < len(fl)}
    return src


def _open_d3dgs(root: Path) -> Source:
    train_path, test_path = root / "train_meta.json", root / "test_meta.json"
    if not train_path.is_file():
        raise DataError(f"{train_path}: not found (Dynamic 3D Gaussians captures need train_meta.json)")
    metas = [read_d3dgs_meta(train_path)] + ([read_d3dgs_meta(test_path)] if test_path.is_file() else [])
    cams: dict[str, Camera] = {}
    files: dict[str, list[str]] = {}
    for meta in metas:
        for cam, fns in zip(cameras_from_d3dgs(meta), meta.files):
            if cam.name in cams:
                raise DataError(f"{meta.path}: camera {cam.name} is also in {train_path.name}; list each camera in one meta")
            cams[cam.name], files[cam.name] = cam, fns
    if not cams:
        raise DataError(f"{train_path}: lists no cameras")
    names = sorted(cams, key=int)
    proper, mirror = proper_world([cams[n] for n in names], train_path)
    cams = dict(zip(names, proper))
    # the metas hold every frame's name: a missing file is an error now, not hours into training
    images = [[root / "ims" / f for f in files[n]] for n in names]
    _require_files(images, ", but the metas list it (restore it, or drop its timestep from the metas)")
    src = _image_source("d3dgs", root, names, images, [cams[n] for n in names],
                        [str(i) for i in metas[1].cam_ids] if len(metas) > 1 else [names[0]])
    if (root / "seg").is_dir():  # masks per camera: captures publish them for the training cameras only
        masks = [_d3dgs_masks(root, files[n]) for n in names]
        src.masks = masks if any(m is not None for m in masks) else None
    src.world_mirror, src.calibration, src.poses_by_hand = mirror, train_path, True
    if mirror is not None:
        src.extra["world_mirrored"] = "x"  # recorded in scene.json: the scene's x axis is the file's -x
    points = root / "init_pt_cld.npz"
    if points.is_file():
        xyz = _read_init_points(points)
        src.hint_points = xyz if mirror is None else xyz @ mirror[:3, :3].T  # the cameras' mirror
        src.depth_hints(src.cameras)
    return src


def _d3dgs_masks(root: Path, fns: list[str]) -> list[Path] | None:
    """A camera's mask files (seg/ mirrors ims/, as .png), or None when it has none of them;
    whether it has all it needs is checked for the frames used (Source.camera_has_masks)."""
    paths = [(root / "seg" / f).with_suffix(".png") for f in fns]
    return paths if any(p.is_file() for p in paths) else None


MIN_HINT_POINTS = 20  # a camera that sees fewer of the initial points gets no depth hint


def point_hints(xyz: np.ndarray, cams: Sequence[Camera]) -> list[list[float] | None]:
    """Per-camera (near, far) depth hints from a capture's own points (Dynamic 3D Gaussians
    ``init_pt_cld.npz``: key ``data``, (N, 7) rows of x y z, r g b in 0..1, segmentation): the
    1st and 99th percentile depth of the points a camera sees, or None when it sees fewer than
    MIN_HINT_POINTS. Only a hint: the stereo takes a camera's depth range from the measured
    points and trusts these to within a factor 10 (atgs.data.mvs.views.depth_ranges); the points
    never enter the scene (their positions were reconstructed elsewhere, and may be loose)."""
    hints = []
    for cam in cams:
        z = _visible_depths(cam, xyz)
        ok = len(z) >= MIN_HINT_POINTS
        hints.append([float(np.percentile(z, 1)), float(np.percentile(z, 99))] if ok else None)
    return hints


def _read_init_points(path: Path) -> np.ndarray:
    """The finite xyz rows of ``init_pt_cld.npz``."""
    fix = "fix it or remove it (it only hints the depth ranges)"
    try:
        loaded = np.load(path, allow_pickle=False)
        if isinstance(loaded, np.ndarray):  # a bare .npy under the .npz name: the array itself
            data = loaded
        else:
            with loaded as f:
                if "data" not in f.files:
                    raise DataError(f"{path}: no array 'data' (expected an (N, 7) array: xyz, rgb, seg); {fix}")
                data = np.asarray(f["data"])
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        why = str(e).splitlines()[0][:120] if str(e).strip() else type(e).__name__
        raise DataError(f"{path}: unreadable ({why}); {fix}") from None
    if data.ndim != 2 or data.shape[1] < 3 or data.dtype.kind not in "fiu":
        raise DataError(f"{path}: 'data' is a {data.dtype} array of shape {data.shape}, expected (N, 7) numbers; {fix}")
    xyz = data[:, :3].astype(np.float64)
    return xyz[np.all(np.isfinite(xyz), axis=1)]


def _visible_depths(cam: Camera, xyz: np.ndarray) -> np.ndarray:
    """Depths of the points in front of ``cam`` that fall inside its image."""
    _, _, z, inside = project(cam, xyz)
    return z[inside]


def _require_files(per_camera: list[list[Path]], fix: str) -> None:
    for paths in per_camera:
        missing = next((p for p in paths if not p.is_file()), None)
        if missing is not None:
            raise DataError(f"{missing}: not found{fix}")
