"""An N3DV-like training scene held in memory, for the training-speed rows of bench/gpu.py.

N3DV (Neural 3D Video) captures: ~20 cameras of a forward-facing rig, 2704x2028 videos trained
at half size, 1352x1014. This builds that camera set over the built-in synthetic scene
(``atgs.data.synth.scene``, ``small-motion``: N3DV-like slow, local motion): 20 cameras on a
front-facing arc, rendered with its mesh renderer (``atgs.data.synth.mesh_renderer``) at any size, a
few frames, and keyframe points sampled from the true surfaces (a speed benchmark needs the
anchor counts of a real scene, not triangulation). Nothing is written to disk: the trainer's
image cache holds every image, so steps/s measures training, not PNG decoding.
"""

from __future__ import annotations

import numpy as np

from atgs.data.scene import MemoryScene
from atgs.data.synth.scene import SynthConfig, SynthScene, sample_surface
from atgs.progress import progress_bar
from atgs.timeline import evenly_spaced

N3DV_SIZE = (1352, 1014)


def n3dv_like_scene(size: tuple[int, int] = N3DV_SIZE, cameras: int = 20, frames: int = 6, keyframes: int = 3,
                    points_per_keyframe: int = 10_000, arc_deg: float = 100.0, fov_x_deg: float = 50.0,
                    progress: bool = True) -> MemoryScene:
    """``cameras`` cameras on a front-facing ``arc_deg`` arc (N3DV's horizontal field of view is
    about 50 degrees), ``frames`` frames of ``size``, ``keyframes`` keyframes of points."""
    from atgs.data.synth.mesh_renderer import MeshRenderer

    W, H = size
    cfg = SynthConfig(frames=frames, cameras=cameras, width=W, height=H, preset="small-motion",
                      arc_deg=arc_deg, fov_x_deg=fov_x_deg)
    synth = SynthScene(cfg)
    cams = synth.cameras()
    renderer = MeshRenderer(synth, W, H)
    images = {}
    try:
        with progress_bar(frames * cameras, f"N3DV-like scene {W}x{H}", unit="img", enabled=progress) as bar:
            for f in range(frames):
                renderer.set_frame(f)
                for ci, cam in enumerate(cams):
                    images[(ci, f)] = renderer.render(cam)
                    bar.update(1)
    finally:
        renderer.release()
    kf = evenly_spaced(frames, keyframes)
    rng = np.random.default_rng(0)
    pts = [sample_surface(synth, f, points_per_keyframe, rng) for f in kf]
    points = np.concatenate(pts).astype(np.float32)
    point_kf = np.repeat(np.arange(len(kf)), [len(p) for p in pts])
    bounds = np.stack([points.min(0), points.max(0)]).astype(np.float64)
    return MemoryScene(cams, frames, cfg.fps, kf, points, point_kf, [], images, bounds)
