"""Writers for the dataset layouts that ``atgs-prepare`` reads (used by tests and for
converting a scene to another layout): COLMAP frame folders and EasyVolcap folders."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from PIL import Image

from atgs.cameras import Camera
from atgs.data.camera_formats import cameras_to_reconstruction, write_easyvolcap


def write_colmap_frames_layout(root: Path, cameras: Sequence[Camera], frames_fn: Callable[[int, int], np.ndarray],
                               num_frames: int, model_in_first_frame: bool = False) -> Path:
    """``frameNNNNNN/images/<cam>.png`` + a COLMAP model (``sparse/0``) with the frame-0 image names."""
    root = Path(root)
    for f in range(num_frames):
        d = root / f"frame{f:06d}" / "images"
        d.mkdir(parents=True, exist_ok=True)
        for ci, cam in enumerate(cameras):
            Image.fromarray(np.asarray(frames_fn(ci, f), np.uint8)).save(d / f"{cam.name}.png", compress_level=1)
    rec = cameras_to_reconstruction(cameras, [f"{c.name}.png" for c in cameras])
    model = (root / "frame000000" / "sparse" / "0") if model_in_first_frame else (root / "sparse" / "0")
    model.mkdir(parents=True, exist_ok=True)
    rec.write(str(model))
    return root


def write_easyvolcap_layout(root: Path, cameras: Sequence[Camera], frames_fn: Callable[[int, int], np.ndarray],
                            num_frames: int, ext: str = ".png") -> Path:
    """``intri.yml`` + ``extri.yml`` + ``images/<cam>/<frame:06d>.png``."""
    root = Path(root)
    write_easyvolcap(root, cameras)
    for ci, cam in enumerate(cameras):
        d = root / "images" / cam.name
        d.mkdir(parents=True, exist_ok=True)
        for f in range(num_frames):
            Image.fromarray(np.asarray(frames_fn(ci, f), np.uint8)).save(d / f"{f:06d}{ext}")
    return root
