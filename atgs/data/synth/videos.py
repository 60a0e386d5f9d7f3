"""Built-in synthetic multi-view videos (``atgs-synth``) and the cached default scene.

``synthesize`` renders a :class:`SynthScene` with the mesh renderer and writes the N3DV layout
(``camXX.mp4`` + ``poses_bounds.npy``) so that synthetic data goes through the same
``atgs-prepare`` path as real captures, plus ``synth.json``: the config that rebuilds the exact
ground-truth geometry (see :func:`load_ground_truth`) and the true near/far of every camera
(``true_near_far``; ``cfg.bounds`` chooses what poses_bounds.npy states, see :func:`stated_bounds`)
and, with ``cfg.exposure``, each camera's (gain, offset) (``exposure``): the frames are written as
each camera records them (atgs.data.synth.mesh_renderer applies it), never as rendered.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from atgs.data.camera_formats import cameras_to_poses_bounds
from atgs.data.synth.scene import SynthConfig, SynthScene, sample_surface
from atgs.geometry.projection import project
from atgs.io.atomic import atomic_dir, interprocess_lock

SIDECAR = "synth.json"
SYNTH_VERSION = 2  # bump when the scene content changes, to invalidate caches
PREPARE_VERSION = 6  # bump when atgs-prepare's output changes (2: dense stereo keyframe points, 3: surface extension,
#                      4: motion points, 5: motion points at 8 instead of 4 keyframes per geometry interval,
#                      6: seeded COLMAP verification: every cache holds the same points, not its own draw)


@dataclass(frozen=True)
class EncodeConfig:
    """How the videos are encoded. The default is lossless RGB H.264 (exact ground truth)."""

    codec: str = "libx264rgb"  # or "libx264" for ordinary YUV files
    crf: int = 0  # 0 = lossless with libx264rgb
    pix_fmt: str | None = None  # rgb24 for libx264rgb, yuv444p/yuv420p for libx264


def synthesize(out: str | Path, cfg: SynthConfig = SynthConfig(), enc: EncodeConfig = EncodeConfig(),
               overwrite: bool = False, progress: bool = True, depth: bool = False) -> Path:
    """Render ``cfg`` into an N3DV-layout directory ``out`` (written atomically). ``depth`` also
    writes the true depth of every frame: ``depth/<frame:06d>.npz``, one float32 (H,W) array per
    camera name, the OpenCV z of the nearest surface at each pixel center (0: none)."""
    from tqdm import tqdm

    from atgs.data.synth.mesh_renderer import MeshRenderer
    from atgs.io.video import VideoWriter

    if cfg.frames < 1 or cfg.cameras < 2 or cfg.width < 16 or cfg.height < 16:
        raise ValueError("need frames >= 1, cameras >= 2 and a resolution of at least 16x16")
    t0 = time.perf_counter()
    out = Path(out)
    scene = SynthScene(cfg)
    cams = scene.cameras()
    with atomic_dir(out, overwrite) as tmp:
        renderer = MeshRenderer(scene, cfg.width, cfg.height)
        writers = [VideoWriter(tmp / f"{c.name}.mp4", cfg.width, cfg.height, cfg.fps, enc.codec, enc.crf, enc.pix_fmt)
                   for c in cams]
        try:
            with tqdm(total=cfg.frames * len(cams), desc="synth render+encode", unit="img", disable=not progress) as bar:
                if depth:
                    (tmp / "depth").mkdir()
                for f in range(cfg.frames):
                    renderer.set_frame(f)
                    for cam, w in zip(cams, writers):
                        w.write(renderer.render(cam))
                        bar.update(1)
                    if depth:
                        np.savez_compressed(tmp / "depth" / f"{f:06d}.npz",
                                            **{c.name: renderer.render_depth(c) for c in cams})
        finally:
            for w in writers:
                w.close()
            renderer.release()
        near_far = _near_far(scene, cams)
        np.save(tmp / "poses_bounds.npy", cameras_to_poses_bounds(cams, stated_bounds(near_far, cfg.bounds)))
        side = scene.describe()
        side.update({"format": "atgs-synth", "version": SYNTH_VERSION, "encoding": enc.__dict__,
                     "test_cameras": [cams[0].name], "true_near_far": near_far.tolist(),
                     "seconds": time.perf_counter() - t0})
        (tmp / SIDECAR).write_text(json.dumps(side, indent=1))
    return out


def _near_far(scene: SynthScene, cams) -> np.ndarray:
    pts = sample_surface(scene, 0, 20000)
    nf = []
    for c in cams:
        _, _, z, vis = project(c, pts)
        zz = z[vis] if vis.any() else z[z > 0]
        nf.append([0.9 * np.percentile(zz, 0.5), 1.1 * np.percentile(zz, 99.5)])
    return np.array(nf)


def stated_bounds(near_far: np.ndarray, bounds: str) -> np.ndarray:
    """The (N,2) near/far that poses_bounds.npy states for the true ones (SynthConfig.bounds), to
    test readers against wrong dataset bounds: "true" as measured; "loose" near/10 and far*10;
    "narrow" both pulled 3/4 of the way to their geometric mean m (m - (m - near)/4, m + (far - m)/4:
    true 2-12 m is stated 4.2-6.7 m, most surfaces fall outside); "none" 0/0, which the readers
    take as missing (atgs.data.mvs.views.depth_ranges uses a hint only where 0 < near < far)."""
    near, far = near_far[:, 0], near_far[:, 1]
    m = np.sqrt(near * far)
    stated = {"true": (near, far), "loose": (near / 10, far * 10), "narrow": (m - (m - near) / 4, m + (far - m) / 4),
              "none": (0 * near, 0 * far)}[bounds]
    return np.stack(stated, 1)


def load_ground_truth(src: str | Path) -> SynthScene:
    """Rebuild the exact ground-truth scene from a synthesized directory (or its synth.json)."""
    p = Path(src)
    p = p / SIDECAR if p.is_dir() else p
    side = json.loads(p.read_text())
    return SynthScene(SynthConfig.from_dict(side["config"]))


def default_config() -> SynthConfig:
    """The default scene for training without user data: 12 cameras x 120 frames, 256x192."""
    return SynthConfig()


def ensure_default_scene(cache_dir: str | Path, cfg: SynthConfig | None = None, keyframes: int = 6,
                         progress: bool = True) -> Path:
    """Prepared directory of a synthetic scene, synthesized and prepared once, then cached.

    The cache key covers the config, the keyframe count and the synth/scene format versions
    (the prepared scene sits in a subdirectory named by PREPARE_VERSION);
    a half-written cache entry is never visible (both steps write atomically), and processes
    asking for the same entry at once build it once (the others wait on a lock file).
    """
    from atgs.data.prepare import PrepareConfig, prepare
    from atgs.data.scene import SCENE_VERSION, PreparedScene

    cfg = cfg or default_config()
    key = json.dumps({"cfg": cfg.to_dict(), "k": keyframes, "v": [SYNTH_VERSION, SCENE_VERSION]}, sort_keys=True)
    digest = hashlib.sha1(key.encode()).hexdigest()[:10]
    base = Path(cache_dir) / f"synth-{cfg.preset}-{digest}"
    # the videos stay cached under the same key; the prepared scene is rebuilt when the keyframe
    # points change (PREPARE_VERSION), not left stale
    prepared = base / ("prepared" if PREPARE_VERSION == 1 else f"prepared-v{PREPARE_VERSION}")
    with interprocess_lock(base.with_name(base.name + ".lock")):
        if (prepared / "scene.json").is_file():
            try:
                PreparedScene.load(prepared)
                return prepared
            except Exception:  # noqa: BLE001 - a damaged cache is rebuilt below
                pass
        raw = base / "raw"
        if not (raw / SIDECAR).is_file():
            synthesize(raw, cfg, overwrite=True, progress=progress)
        prepare(PrepareConfig(src=raw, out=prepared, keyframes=keyframes, overwrite=True, progress=progress))
    return prepared


def with_overrides(cfg: SynthConfig, **kw) -> SynthConfig:
    return replace(cfg, **{k: v for k, v in kw.items() if v is not None})
