"""A synthetic web export of any length, without a trained model: a cloud of Gaussians that
sways from frame to frame, written with the exporter's own chunk writer
(:func:`atgs.web.stream_format.quantize_chunk`, :func:`~atgs.web.stream_format.pack_chunk`) and
player (:func:`atgs.web.export.copy_player`).

For what a real export of that length is too slow to make here: the player's memory over a
1,000-frame video (bench/web.py --part memory) and the browser tests of streaming and failures
(tests/test_web_player_failures.py), which need a picture, not a trained one.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import numpy as np
from PIL import Image

from atgs.io.atomic import write_json_atomic
from atgs.web.export import STREAM_DIR, copy_player
from atgs.web.manifest import (ENVIRONMENT_NAME, FORMAT, MANIFEST_NAME, VERSION, ChunkInfo, chunk_file_name,
                               render_numerics)
from atgs.web.stream_format import StreamFrame, pack_chunk, quantize_chunk

CAMERA_DISTANCE = 4.0
SWAY = 0.05  # how far (scene units) a Gaussian moves about its place
SWAY_PERIOD = 48  # frames
# Per-frame noise (scene units, colour units) so that frames do not compress to nothing: about
# 8 bytes a Gaussian a frame, twice a trained model's (docs/web.md), for fewer Gaussians to draw.
POSITION_NOISE = 0.002
COLOUR_NOISE = 0.01


def _cameras(width: int, height: int) -> list[dict]:
    """Two cameras looking at the origin from CAMERA_DISTANCE: straight on (held out) and 30 degrees to the side."""
    cams = []
    for k, angle in enumerate((0.0, np.pi / 6)):
        c, s = np.cos(angle), np.sin(angle)
        R = np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])  # OpenCV axes turned about y
        w2c = np.eye(4)
        w2c[:3, :3] = R
        w2c[:3, 3] = [0, 0, CAMERA_DISTANCE]
        f = 1.2 * width
        cams.append({"name": f"cam{k:02d}", "width": width, "height": height, "fx": f, "fy": f, "cx": width / 2,
                     "cy": height / 2, "w2c": [float(v) for v in w2c.reshape(-1)], "held_out": k == 0})
    return cams


def synthetic_export(out: str | Path, *, frames: int, gaussians: int, chunk_frames: int = 8, width: int = 96,
                     height: int = 72, environment: bool = False, background=(0.2, 0.4, 0.6), seed: int = 0) -> dict:
    """Write a web export of ``frames`` frames of ``gaussians`` Gaussians to ``out`` (a new
    folder); with ``environment``, an environment map (a colour gradient) too. Returns the manifest."""
    out = Path(out)
    stream = out / STREAM_DIR
    stream.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    G = gaussians
    place = rng.normal(size=(G, 3)) * 0.45
    phase = rng.uniform(0, 2 * np.pi, size=(G, 3))
    scales = np.exp(rng.uniform(np.log(0.02), np.log(0.08), size=(G, 3)))
    quats = rng.normal(size=(G, 4))
    opacities = rng.uniform(0.5, 0.95, size=G)
    colors = rng.uniform(0.05, 0.95, size=(G, 3))
    ids = np.arange(G)

    def frame(t: int) -> StreamFrame:
        means = place + SWAY * np.sin(2 * np.pi * t / SWAY_PERIOD + phase) + rng.normal(0, POSITION_NOISE, (G, 3))
        tint = np.clip(colors + rng.normal(0, COLOUR_NOISE, (G, 3)), 0, 1)
        return StreamFrame(ids, means, scales, quats, opacities, tint)

    chunks: list[ChunkInfo] = []
    for start in range(0, frames, chunk_frames):
        q = quantize_chunk([frame(t) for t in range(start, min(frames, start + chunk_frames))])
        data = pack_chunk(q)
        name = chunk_file_name(len(chunks))
        (stream / name).write_bytes(data)
        chunks.append(ChunkInfo(name, q.num_frames, q.num_gaussians, q.static, len(data)))
    env = None
    if environment:  # azimuth along x, elevation along y: every direction a different colour
        u, v = np.meshgrid(np.linspace(0, 1, 64), np.linspace(0, 1, 32))
        texels = np.stack([u, v, 1 - u], axis=-1)
        Image.fromarray((texels * 255).round().astype(np.uint8), "RGB").save(stream / ENVIRONMENT_NAME)
        env = {"file": ENVIRONMENT_NAME, "basis": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]}
    manifest = {
        "format": FORMAT, "version": VERSION, "fps": 30.0, "frames": list(range(frames)),
        "chunk_frames": chunk_frames, "chunks": [asdict(c) for c in chunks],
        "cameras": _cameras(width, height), "background": [float(c) for c in background], "environment": env,
        "render": render_numerics(), "scene": {"center": [0.0, 0.0, 0.0], "radius": CAMERA_DISTANCE},
        "source": {"synthetic": {"gaussians": G, "seed": seed}},
    }  # fmt: skip
    write_json_atomic(stream / MANIFEST_NAME, manifest)
    copy_player(out)
    return manifest
