"""stream/manifest.json of a web export (docs/web.md, "manifest.json"): what the player reads
before any chunk, built from the model and the chunks written."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from atgs.cameras import Camera
from atgs.model.near_plane import near_of
from atgs.render.constants import ALPHA_MAX, ALPHA_MIN, CLAMP_MARGIN, DILATION, NEAR, RADIUS_SIGMAS
from atgs.viewer.scene_utils import default_camera, orbit_center

FORMAT = "atgs-web"
VERSION = 1
MANIFEST_NAME = "manifest.json"
ENVIRONMENT_NAME = "environment.png"


@dataclass
class ChunkInfo:
    """One chunk file's entry in the manifest."""

    file: str
    frames: int
    gaussians: int  # G: the union over its frames
    static: int
    bytes: int  # the file's exact size


def chunk_file_name(index: int) -> str:
    return f"chunk_{index:06d}.bin"


def camera_entry(cam: Camera, held_out: bool) -> dict[str, Any]:
    return {"name": cam.name, "width": cam.width, "height": cam.height, "fx": cam.fx, "fy": cam.fy,
            "cx": cam.cx, "cy": cam.cy, "w2c": [float(v) for v in cam.w2c.reshape(-1)], "held_out": held_out}


def render_numerics(near: float = NEAR) -> dict[str, float]:
    """The rasterizer's numbers, so the browser draws what atgs-view draws; ``near``: the
    model's near plane (atgs.model.near_plane)."""
    return {"near": float(near), "dilation": DILATION, "alpha_min": ALPHA_MIN, "alpha_max": ALPHA_MAX,
            "extent": RADIUS_SIGMAS, "clamp_margin": CLAMP_MARGIN}


def scene_entry(model) -> dict[str, Any]:
    """Where orbiting starts: the viewer's pivot, and the training cameras' mean distance from it
    (without cameras, the distance at which atgs-view's default camera frames frame 0)."""
    center = np.asarray(orbit_center(model), dtype=np.float64)
    cams = list(model.cameras)
    if cams:
        radius = float(np.mean([np.linalg.norm(c.center - center) for c in cams]))
    else:
        framing = default_camera(model.gaussians_at_frame(0).means.cpu().numpy())
        radius = float(np.linalg.norm(framing.center - center))
    return {"center": [float(v) for v in center], "radius": max(radius, 1e-3)}


def stream_entries(model, frames: list[int], source: dict[str, Any]) -> dict[str, Any]:
    """What every kind of stream's manifest holds: the frames, the cameras, the background and the
    render numerics (stream/environment.png holds the model's background by direction, if any)."""
    held_out = set(getattr(model, "test_camera_names", []))
    env = getattr(model, "environment", None)
    return {
        "format": FORMAT, "version": VERSION,
        "fps": float(model.fps),
        "frames": [int(f) for f in frames],
        "cameras": [camera_entry(c, c.name in held_out) for c in model.cameras],
        "background": [float(c) for c in getattr(model, "background", (0.0, 0.0, 0.0))],
        "environment": None if env is None else {"file": ENVIRONMENT_NAME,
                                                 "basis": [float(v) for v in np.asarray(env.basis).reshape(-1)]},
        "render": render_numerics(near_of(model)),
        "scene": scene_entry(model),
        "source": source,
    }  # fmt: skip


def chunk_entries(chunk_frames: int, chunks: list[ChunkInfo]) -> dict[str, Any]:
    """A Gaussian stream's own manifest entries: its chunk files."""
    return {"chunk_frames": int(chunk_frames), "chunks": [asdict(c) for c in chunks]}
