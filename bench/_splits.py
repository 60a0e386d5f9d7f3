"""Held-out PSNR split by what the pixels show, for the benches of the built-in scene.

- moving / static: a pixel moves at a frame when it differs from its camera's background
  (atgs.data.moving_points.motion_mask at full size);
- seen / unseen: a pixel is *seen* when the surface it shows (the synthetic scene's true depth)
  is visible (in the image, not occluded) in at least one training camera. Nothing can recover
  the colour of an unseen pixel, so its error is not the model's. ``by_views`` splits the pixels
  further by how many training cameras see their surface (one camera: colour, but no depth).
- temporal: the PSNR of the frame-to-frame change, (R[f+1] - R[f]) against (G[f+1] - G[f]),
  over the consecutive pairs of frames where the model's keyframe window changes ("switch") and
  over the others: popping when the active anchor set changes shows as a lower switch figure.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from atgs.geometry.projection import project
from atgs.geometry.rays import pixel_rays, to_world

VIEW_BINS = 7  # the per-view-count split: 0, 1, ..., 5 and 6 or more training cameras


def _visible_count(gt, scene, ci: int, frame: int, renderers: dict) -> np.ndarray:
    """(H, W) number of training cameras that see the surface of test camera ``ci``'s pixels."""
    from atgs.data.synth.mesh_renderer import MeshRenderer

    def depth(cam):
        key = (cam.width, cam.height)
        if key not in renderers:
            renderers[key] = MeshRenderer(gt, *key)
        r = renderers[key]
        r.set_frame(frame)
        return r.render_depth(cam)

    cam = scene.cameras[ci]
    d0 = depth(cam)
    v, u = np.nonzero(d0 > 0)
    z = d0[v, u].astype(np.float64)
    world = to_world(cam, pixel_rays(cam, u + 0.5, v + 0.5) * z[:, None])
    count = np.zeros(d0.shape, np.int32)
    for j in scene.train_indices:
        tc = scene.cameras[j]
        dj = depth(tc)
        pu, pv, zj, inside = project(tc, world, near=1e-6)
        ok = np.zeros(len(world), bool)
        iu, iv = pu[inside].astype(np.int64), pv[inside].astype(np.int64)
        near = dj[iv, iu]
        ok[inside] = (near > 0) & (np.abs(near - zj[inside]) < 0.03 * zj[inside])  # not occluded
        count[v[ok], u[ok]] += 1
    return count


def held_out_splits(ckpt: Path, scene_dir: Path, every: int = 8) -> dict:
    """PSNR of the held-out cameras (every ``every``-th frame) on moving / static pixels and, for
    a scene prepared from atgs-synth output, on seen / unseen pixels (see the module doc)."""
    import torch

    import atgs
    from atgs.checkpoint import read_checkpoint
    from atgs.data.motion_measure import box_downsample
    from atgs.data.moving_points import MotionPointsConfig, background, motion_mask
    from atgs.data.scene import PreparedScene
    from atgs.render import rasterize_gaussians
    from atgs.timeline import evenly_spaced

    scene, model, cfg = PreparedScene.load(scene_dir), atgs.load(ckpt), MotionPointsConfig()
    bg_rgb = (read_checkpoint(ckpt).get("train_config") or {}).get("background") or (0.0, 0.0, 0.0)
    # what the run trained over: its background by direction if it has one, else its colour
    bg_t = model.environment or torch.tensor(bg_rgb, dtype=torch.float32)
    gt_scene = None
    if (Path(scene_dir) / "synth.json").is_file():
        from atgs.data.synth.videos import load_ground_truth

        gt_scene = load_ground_truth(Path(scene_dir) / "synth.json")
    se: dict[str, float] = {}
    n: dict[str, int] = {}

    def add(name: str, err: np.ndarray, sel: np.ndarray) -> None:
        se[name] = se.get(name, 0.0) + float(err[sel].sum())
        n[name] = n.get(name, 0) + int(sel.sum())

    renderers: dict = {}
    try:
        for ci in scene.test_indices:
            side = max(scene.cameras[ci].width, scene.cameras[ci].height)
            bg = background([box_downsample(scene.image_uint8(ci, f), side)
                             for f in evenly_spaced(scene.num_frames, 48)])
            for f in range(0, scene.num_frames, every):
                gt = scene.image_uint8(ci, f)
                with torch.no_grad():
                    img = rasterize_gaussians(model.gaussians_at_frame(f), scene.cameras[ci],
                                              background=bg_t, near=model.near).image.clamp(0, 1).numpy()
                err = ((img - gt.astype(np.float32) / 255.0) ** 2).mean(-1)
                mask = motion_mask(box_downsample(gt, side), bg, cfg)
                add("all", err, np.ones_like(mask))
                add("moving", err, mask)
                add("static", err, ~mask)
                if gt_scene is not None:
                    count = _visible_count(gt_scene, scene, ci, f, renderers)
                    seen = count > 0
                    add("seen", err, seen)
                    add("unseen", err, ~seen)
                    for k in range(VIEW_BINS):  # by how many training cameras see the surface
                        add(f"views{k}", err, count == k if k < VIEW_BINS - 1 else count >= k)
            prev = None  # frame-to-frame change over every consecutive pair
            for f in range(scene.num_frames):
                gt = scene.image_uint8(ci, f).astype(np.float32) / 255.0
                with torch.no_grad():
                    img = rasterize_gaussians(model.gaussians_at_frame(f), scene.cameras[ci],
                                              background=bg_t, near=model.near).image.clamp(0, 1).numpy()
                window = model.timeline.window_of_frame(f)
                if prev is not None:
                    d = ((img - prev[0]) - (gt - prev[1])) ** 2
                    add("switch" if window != prev[2] else "steady", d.mean(-1), np.ones(d.shape[:2], bool))
                prev = (img, gt, window)
    finally:
        for r in renderers.values():
            r.release()
    db = lambda k: round(-10 * math.log10(se[k] / n[k]), 2) if n.get(k) else None  # noqa: E731
    out = {"psnr_moving": db("moving"), "psnr_static": db("static"),
           "moving_fraction": round(n["moving"] / max(n["all"], 1), 4), "every_nth_frame": every,
           "psnr_change_switch": db("switch"), "psnr_change_steady": db("steady"),
           "background": [float(c) for c in bg_rgb], "background_by_direction": model.environment is not None}
    if gt_scene is not None:
        out.update({"psnr_seen": db("seen"), "psnr_unseen": db("unseen"),
                    "unseen_fraction": round(n.get("unseen", 0) / max(n["all"], 1), 4),
                    "unseen_error_share": round(se.get("unseen", 0.0) / max(se["all"], 1e-12), 3),
                    # seen by 0, 1, ..., VIEW_BINS - 1 or more training cameras: share of the
                    # pixels, PSNR, share of the squared error
                    "by_views": [{"views": k if k < VIEW_BINS - 1 else f">={k}",
                                  "fraction": round(n.get(f"views{k}", 0) / max(n["all"], 1), 4),
                                  "psnr": db(f"views{k}"),
                                  "error_share": round(se.get(f"views{k}", 0.0) / max(se["all"], 1e-12), 3)}
                                 for k in range(VIEW_BINS)]})
    return out
