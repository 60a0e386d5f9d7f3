"""Synthetic scene ground truth: exact surface distances, renderer/camera agreement, motion."""

from __future__ import annotations

import numpy as np

from atgs.data.synth.mesh_renderer import MeshRenderer
from atgs.data.synth.scene import (PRESETS, SynthConfig, SynthScene, distance_to_surfaces, point_triangle_distance,
                                   sample_surface)

CFG = SynthConfig(frames=2, cameras=12, width=256, height=192)


def test_point_triangle_distance_matches_brute_force() -> None:
    rng = np.random.default_rng(0)
    n = 60
    a, b, c = rng.normal(size=(3, n, 3))
    p = rng.normal(size=(n, 3)) * 1.5
    exact = point_triangle_distance(p, a, b, c)
    # slow reference: dense barycentric sampling of each triangle (an upper bound, tight to ~grid step)
    k = 200
    u, v = np.meshgrid(np.linspace(0, 1, k), np.linspace(0, 1, k))
    keep = u + v <= 1
    u, v = u[keep], v[keep]
    for i in range(n):
        pts = a[i] + u[:, None] * (b[i] - a[i]) + v[:, None] * (c[i] - a[i])
        brute = np.linalg.norm(pts - p[i], axis=1).min()
        step = max(np.linalg.norm(b[i] - a[i]), np.linalg.norm(c[i] - a[i])) / (k - 1)
        assert exact[i] <= brute + 1e-12
        assert exact[i] >= brute - step


def _bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    x, y = uv[:, 0] - 0.5, uv[:, 1] - 0.5
    x0 = np.clip(np.floor(x).astype(int), 0, img.shape[1] - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, img.shape[0] - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    return (img[y0, x0] * (1 - fx) * (1 - fy) + img[y0, x0 + 1] * fx * (1 - fy)
            + img[y0 + 1, x0] * (1 - fx) * fy + img[y0 + 1, x0 + 1] * fx * fy)


def test_rendered_pixels_agree_with_camera_projection() -> None:
    """Ground points seen by two cameras have the same color in both renders exactly where
    Camera.project puts them, and less often one pixel away: renderer and camera model agree."""
    scene = SynthScene(CFG)
    r = MeshRenderer(scene, CFG.width, CFG.height)
    r.set_frame(0)
    cams = scene.cameras()
    imgs = [r.render(c).astype(np.float64) for c in cams[:2]]
    r.release()
    p = sample_surface(scene, 0, 60000, max_radius=4.0)
    p = p[np.abs(p[:, 2]) < 1e-9]  # the ground plane
    uv = [c.project(p)[0] for c in cams[:2]]
    ok = np.ones(len(p), bool)
    for q in uv:
        ok &= (q[:, 0] > 2) & (q[:, 0] < CFG.width - 3) & (q[:, 1] > 2) & (q[:, 1] < CFG.height - 3)
    a = _bilinear(imgs[0], uv[0][ok])

    def agreeing(shift) -> float:  # share of points whose colors match (occlusions and mip blur do not)
        return float(np.mean(np.abs(a - _bilinear(imgs[1], uv[1][ok] + shift)).sum(1) < 15))

    f0 = agreeing(np.zeros(2))
    for s in ([1.0, 0], [-1.0, 0], [0, 1.0], [0, -1.0]):
        assert f0 > 1.2 * agreeing(np.array(s)), (f0, s)


def test_motion_presets() -> None:
    big = SynthScene(SynthConfig(frames=60, preset="large-motion", texture_size=64))
    small = SynthScene(SynthConfig(frames=60, preset="small-motion", texture_size=64))
    assert PRESETS["large-motion"].cross_speed > 5 * PRESETS["small-motion"].cross_speed

    def track(scene, name):
        obj = next(o for o in scene.objects if o.name == name)
        return np.array([scene.model_matrix(obj, f)[:3, 3] for f in range(0, 240, 2)])

    # the crossing box moves at the preset speed (finite difference of the analytic path)
    x = track(big, "crosser")
    speed = np.linalg.norm(np.diff(x, axis=0), axis=1) / (2 / 30)
    assert abs(np.median(speed) - PRESETS["large-motion"].cross_speed) < 0.1
    # the jumper leaves the scene (fully below the ground) and comes back
    z = track(big, "jumper")[:, 2]
    assert z.min() < -0.32 and z.max() > 0.5
    # large motion moves objects much farther than small motion over the same time
    for name in ("crosser", "orbiter"):
        d_big = np.linalg.norm(np.diff(track(big, name), axis=0), axis=1).sum()
        d_small = np.linalg.norm(np.diff(track(small, name), axis=0), axis=1).sum()
        assert d_big > 4 * d_small
    # the blob deforms: its object-space vertices change over time
    blob = next(o for o in big.objects if o.name == "blob")
    assert np.abs(big.object_space_mesh(blob, 0).positions - big.object_space_mesh(blob, 15).positions).max() > 0.03


def test_true_depth_lies_on_the_surfaces() -> None:
    scene = SynthScene(CFG)
    r = MeshRenderer(scene, CFG.width, CFG.height)
    r.set_frame(1)
    cam = scene.cameras()[4]
    d = r.render_depth(cam)
    r.release()
    assert d.dtype == np.float32 and d.shape == (CFG.height, CFG.width) and (d > 0).mean() > 0.95
    v, u = np.mgrid[0:CFG.height:5, 0:CFG.width:5]
    z = d[v, u].astype(np.float64)
    pc = np.stack([(u + 0.5 - cam.cx) / cam.fx * z, (v + 0.5 - cam.cy) / cam.fy * z, z], -1).reshape(-1, 3)
    X = (pc[z.reshape(-1) > 0] - cam.t) @ cam.R
    # float32 depth of surfaces 3-11 m away: exact to ~1e-6 relative, far below a texel
    assert distance_to_surfaces(scene, 1, X).max() < 1e-4


def test_new_layouts_and_the_unchanged_default_config() -> None:
    from dataclasses import replace

    from atgs.data.synth.scene import LAYOUTS

    d = SynthConfig().to_dict()
    assert "rig" not in d and "texture_contrast" not in d  # cache keys of existing scenes unchanged
    front = replace(SynthConfig(), **LAYOUTS["front6"])
    assert SynthConfig.from_dict(front.to_dict()) == front and front.to_dict()["rig"] == "front"
    cams = SynthScene(front).cameras()
    assert len(cams) == 6 and all(c.forward[1] > 0.9 for c in cams)  # all face +y: front-facing
    assert np.ptp([c.center[1] for c in cams]) < 1e-9 and np.ptp([c.center[0] for c in cams]) > 1.0
    flat = SynthScene(replace(CFG, texture_contrast=0.0))
    assert all(np.ptp(t.reshape(-1, 3), axis=0).max() == 0 for t in flat.textures)
    low = replace(SynthConfig(), **LAYOUTS["ring10-low"])
    assert (low.cameras, low.width, low.height) == (10, 200, 150)


def test_synthesize_writes_true_depth(tmp_path) -> None:
    from atgs.data.synth.videos import synthesize

    cfg = SynthConfig(frames=2, cameras=3, width=48, height=32, texture_size=64)
    out = synthesize(tmp_path / "raw", cfg, progress=False, depth=True)
    scene = SynthScene(cfg)
    r = MeshRenderer(scene, cfg.width, cfg.height)
    for f in range(2):
        r.set_frame(f)
        with np.load(out / "depth" / f"{f:06d}.npz") as z:
            assert sorted(z.files) == [c.name for c in scene.cameras()]
            for c in scene.cameras():
                assert np.array_equal(z[c.name], r.render_depth(c))
    r.release()
