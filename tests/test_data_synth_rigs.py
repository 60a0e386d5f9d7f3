"""Synthetic capture-stage rigs: domes and rings whose cameras see each other, the walking person,
the stated dataset bounds, and the default scene left as it was."""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace

import numpy as np
import pytest

from atgs.data.synth.mesh_renderer import MeshRenderer
from atgs.data.synth.scene import (CAMERA_BEHIND, DOME_TARGET, LAYOUTS, WALK_SPEED, SynthConfig, SynthScene,
                                   distance_to_surfaces, sample_surface)


def layout(name: str, **kw) -> SynthConfig:
    return replace(replace(SynthConfig(frames=2, texture_size=32), **LAYOUTS[name]), **kw)


def test_the_default_config_and_its_cache_key_are_unchanged() -> None:
    from atgs.data.scene import SCENE_VERSION
    from atgs.data.synth.videos import SYNTH_VERSION

    d = SynthConfig().to_dict()
    assert d == {"frames": 120, "cameras": 12, "width": 256, "height": 192, "seed": 0, "preset": "large-motion",
                 "fps": 30.0, "ring_radius": 4.6, "wall_radius": 6.5, "fov_x_deg": 62.0, "arc_deg": 360.0,
                 "texture_size": 512}
    key = json.dumps({"cfg": d, "k": 6, "v": [SYNTH_VERSION, SCENE_VERSION]}, sort_keys=True)
    assert hashlib.sha1(key.encode()).hexdigest()[:10] == "a5c17ef9be"  # ensure_default_scene's key
    dome = layout("dome24", bounds="loose")
    assert SynthConfig.from_dict(dome.to_dict()) == dome
    assert {"rig", "subject", "bounds"} <= set(dome.to_dict()) and "dome_rings" not in dome.to_dict()  # 3: default


def test_dome_cameras_look_at_the_center_and_see_each_other() -> None:
    cfg = layout("dome24", width=160, height=120)
    scene = SynthScene(cfg)
    cams = scene.cameras()
    assert len(cams) == 24 and len({c.name for c in cams}) == 24
    centers = np.array([c.center for c in cams])
    heights, counts = np.unique(np.round(centers[:, 2], 6), return_counts=True)
    assert heights.tolist() == [0.6, 1.7, 3.2] and counts.tolist() == [8, 8, 8]
    radii = np.linalg.norm(centers[:, :2], axis=1)
    assert radii[centers[:, 2] > 3].max() < radii.max() - 0.5  # the high ring is the narrow one
    assert cfg.backdrop_radius == pytest.approx(radii.max() + 0.5)  # the wall just behind the cameras
    to_target = DOME_TARGET - centers
    to_target /= np.linalg.norm(to_target, axis=1, keepdims=True)
    assert np.allclose([c.forward for c in cams], to_target, atol=1e-9)
    # each camera sees other cameras' bodies (drawn: the rendered depth there is the body's), never its own
    bodies = centers - CAMERA_BEHIND * np.array([c.forward for c in cams])
    r = MeshRenderer(scene, cfg.width, cfg.height)
    r.set_frame(0)
    seen, drawn = [], 0
    for i, cam in enumerate(cams):
        uv, z = cam.project(bodies)
        assert z[i] < 0  # its own body is behind it
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        depth = r.render_depth(cam)[uv[inside, 1].astype(int), uv[inside, 0].astype(int)]
        seen.append(int(inside.sum()))
        drawn += int((np.abs(depth - z[inside]) < 0.15).sum())
    r.release()
    assert min(seen) >= 2 and np.median(seen) >= 6, seen  # the high ring sees the low ring across
    assert drawn >= 0.85 * sum(seen)  # the person hides a few


@pytest.mark.parametrize("name, cameras, rings", [("dome12-low", 12, 2), ("ring10", 10, 1), ("sparse4", 4, 1)])
def test_the_other_rigs(name: str, cameras: int, rings: int) -> None:
    cfg = layout(name)
    cams = SynthScene(cfg).cameras()
    centers = np.array([c.center for c in cams])
    assert len(cams) == cameras and len(np.unique(np.round(centers[:, 2], 6))) == rings
    assert (cfg.width, cfg.height) == (200, 150)
    if rings == 1:
        assert np.allclose(np.linalg.norm(centers[:, :2], axis=1), 4.6)
        azimuth = np.sort(np.degrees(np.arctan2(centers[:, 1], centers[:, 0])) % 360)
        assert np.allclose(np.diff(azimuth), 360 / cameras)


def test_the_person_walks_and_its_surfaces_are_the_ground_truth() -> None:
    cfg = layout("dome12-low", frames=60)
    scene = SynthScene(cfg)
    parts = {o.name: o for o in scene.objects if o.name.startswith("person_")}
    assert len(parts) == 6 and "orbiter" in {o.name for o in scene.objects}
    tops = [scene.meshes_at(f) for f in (0, 30)]
    z = [np.concatenate([m.positions[:, 2] for o, m in ms if o.name.startswith("person_")]) for ms in tops]
    assert all(1.72 < zz.max() < 1.78 and zz.min() > -1e-6 for zz in z)  # 1.75 m tall, on the ground
    torso = np.array([scene.model_matrix(parts["person_torso"], f)[:3, 3] for f in range(60)])
    speed = np.linalg.norm(np.diff(torso, axis=0), axis=1) * cfg.fps
    assert np.allclose(speed, WALK_SPEED["large-motion"], rtol=0.01)
    assert np.allclose(np.linalg.norm(torso[:, :2], axis=1), 1.0)
    legs = [np.linalg.inv(scene.model_matrix(parts["person_torso"], f)) @ scene.model_matrix(parts["person_leg_l"], f)
            for f in (0, 10, 20)]
    assert np.ptp([m[0, 3] for m in legs]) > 0.05  # the leg swings in the walker's frame
    # points drawn on the analytic boxes and sphere lie on the rendered triangles
    rng = np.random.default_rng(1)
    for f in (0, 17):
        for name, obj in parts.items():
            M = scene.model_matrix(obj, f)
            if name == "person_head":
                d = rng.normal(size=(40, 3))
                p, tol = 0.12 * d / np.linalg.norm(d, axis=1, keepdims=True), 2e-3  # tessellation sag
            else:
                half = np.abs(obj.mesh.positions).max(0)
                p = rng.uniform(-1, 1, (40, 3)) * half
                axis = rng.integers(0, 3, 40)
                p[np.arange(40), axis] = half[axis] * rng.choice([-1, 1], 40)
                tol = 1e-6  # the meshes are float32
            X = p @ M[:3, :3].T + M[:3, 3]
            assert distance_to_surfaces(scene, f, X).max() < tol, name
    front = scene.model_matrix(parts["person_torso"], 5) @ np.array([0.12 + 0.05, 0, 0, 1])
    assert distance_to_surfaces(scene, 5, front[None, :3])[0] == pytest.approx(0.05, abs=1e-6)
    moving = sample_surface(scene, 5, 500, moving_only=True)
    assert distance_to_surfaces(scene, 5, moving, moving_only=True).max() < 1e-9


@pytest.mark.parametrize("bounds", ["true", "loose", "narrow", "none"])
def test_stated_bounds_are_what_poses_bounds_npy_holds(tmp_path, bounds: str) -> None:
    from atgs.data.camera_formats import cameras_from_poses_bounds
    from atgs.data.mvs.views import depth_ranges
    from atgs.data.synth.videos import synthesize

    cfg = layout("sparse4", frames=1, width=32, height=24, bounds=bounds)
    out = synthesize(tmp_path / "raw", cfg, progress=False)
    side = json.loads((out / "synth.json").read_text())
    true = np.array(side["true_near_far"])
    assert side["config"].get("bounds", "true") == bounds  # written only when not the default
    cams, stated = cameras_from_poses_bounds(np.load(out / "poses_bounds.npy"), [f"cam{i:02d}" for i in range(4)])
    near, far = true.T
    assert true.shape == (4, 2) and np.all((0.3 < near) & (near < far))
    m = np.sqrt(near * far)
    expected = {"true": true, "loose": np.stack([near / 10, far * 10], 1),
                "narrow": np.stack([m - (m - near) / 4, m + (far - m) / 4], 1), "none": np.zeros((4, 2))}[bounds]
    assert np.allclose(stated, expected, rtol=1e-12)
    if bounds == "narrow":
        assert np.all((stated[:, 0] > near) & (stated[:, 1] < far))
    if bounds == "none":  # 0/0 is no hint: the stereo's depth ranges are the camera layout's
        assert depth_ranges(cams, None, hints=[tuple(x) for x in stated]) == depth_ranges(cams, None)


def test_cli_layout_and_bounds(tmp_path) -> None:
    from atgs.cli.synth import main

    assert main([str(tmp_path / "bad"), "--rig", "dome", "--dome-rings", "4", "--frames", "1"]) == 2
    assert not (tmp_path / "bad").exists()
    out = tmp_path / "sparse"
    assert main([str(out), "--layout", "sparse4", "--frames", "1", "--bounds", "none", "--subject", "person"]) == 0
    side = json.loads((out / "synth.json").read_text())
    assert {k: side["config"][k] for k in ("cameras", "width", "rig", "dome_rings", "subject", "bounds")} == {
        "cameras": 4, "width": 200, "rig": "dome", "dome_rings": 1, "subject": "person", "bounds": "none"}
    assert not np.load(out / "poses_bounds.npy")[:, 15:].any() and len(side["true_near_far"]) == 4
    # the stage's ingredients one by one, on any rig
    assert main([str(tmp_path / "bad3"), "--subject", "person", "--people", "3", "--frames", "1"]) == 2
    stage = tmp_path / "ring-stage"
    assert main([str(stage), "--cameras", "4", "--width", "64", "--height", "48", "--frames", "1", "--subject",
                 "person", "--people", "2", "--walls", "grey", "--exposure", "0.3"]) == 0
    side = json.loads((stage / "synth.json").read_text())
    assert {k: side["config"][k] for k in ("people", "walls", "exposure")} == {"people": 2, "walls": "grey",
                                                                              "exposure": 0.3}
    gains = [g for g, _ in side["exposure"].values()]
    assert len(gains) == 4 and min(gains) == pytest.approx(2 ** -0.3) and max(gains) == pytest.approx(2 ** 0.3)


def test_the_stage_layout_is_a_hard_dome() -> None:
    """dome-stage: 27 cameras on 3 rings, two walkers clear of each other, faint grey walls, and
    the other layouts' scenes untouched by the options it adds."""
    cfg = layout("dome-stage", frames=30)
    scene = SynthScene(cfg)
    cams = scene.cameras()
    centers = np.array([c.center for c in cams])
    assert (cfg.width, cfg.height) == (320, 180) and cfg.bounds == "true"  # the bench states them loose
    assert np.unique(np.round(centers[:, 2], 6), return_counts=True)[1].tolist() == [9, 9, 9]
    torso = {p: [scene.model_matrix(next(o for o in scene.objects if o.name == f"{p}_torso"), f)[:3, 3]
                 for f in range(30)] for p in ("person", "person2")}
    gap = np.linalg.norm(np.array(torso["person"]) - np.array(torso["person2"]), axis=1)
    assert gap.min() > 1.0 and np.allclose(np.linalg.norm(np.array(torso["person2"])[:, :2], axis=1), 2.4)
    # the walls: light grey, colourless, faint; the textured dome's walls are not
    for tex, base in ((scene.textures[1], 0.93), (scene.textures[0], 0.62)):
        t = tex.astype(np.float64) / 255
        assert abs(t.mean() - base) < 0.02 and np.ptp(t.mean((0, 1))) < 0.025 and 0.005 < t.std() < 0.04
    assert SynthScene(layout("dome24")).textures[1].astype(np.float64).std() / 255 > 0.1
    plain = SynthScene(replace(cfg, people=1, walls="textured", exposure=0.0))
    assert all(np.array_equal(a, b) for a, b in zip(plain.textures, SynthScene(layout("dome24")).textures))


def test_stage_frames_carry_each_cameras_exposure(tmp_path) -> None:
    """Every camera records gain * rendered + offset, the same at every frame; the written frames
    are exactly that, and the ground truth rendered for a camera carries its exposure too."""
    from atgs.data.synth.videos import synthesize
    from atgs.data.video import iter_frames

    cfg = layout("dome-stage", frames=2, width=64, height=36)
    out = synthesize(tmp_path / "raw", cfg, progress=False)
    side = json.loads((out / "synth.json").read_text())
    scene = SynthScene(cfg)
    gains = np.array([scene.exposure_of(c.name) for c in scene.cameras()])
    assert side["exposure"] == {k: list(v) for k, v in scene.exposure.items()} and len(gains) == 27
    assert 2 ** (2 * cfg.exposure) == pytest.approx(gains[:, 0].max() / gains[:, 0].min())  # +-0.35 stops
    assert np.ptp(gains[:, 1]) > 0.05 and scene.exposure_of("novel") == (1.0, 0.0)
    r = MeshRenderer(scene, cfg.width, cfg.height)
    means = []
    for cam in scene.cameras()[:9]:
        written = [img for _, img in iter_frames(out / f"{cam.name}.mp4")]
        for f, img in enumerate(written):
            r.set_frame(f)
            raw = r.render(cam, exposed=False).astype(np.float64)
            g, o = scene.exposure_of(cam.name)
            assert np.abs(img - np.clip(np.round(g * raw + 255 * o), 0, 255)).max() <= 1  # lossless RGB video
            assert np.array_equal(r.render(cam), img)
        means.append(written[0].mean() / r.render(cam, exposed=False).mean())
    r.release()
    assert np.ptp(means) > 0.2  # the same wall looks brighter in some cameras than in others


def _blocks(a: np.ndarray, n: int = 6) -> np.ndarray:
    """(H/n, W/n, n*n): the pixels of each n x n block."""
    hb, wb = a.shape[0] // n, a.shape[1] // n
    return a[:hb * n, :wb * n].reshape(hb, n, wb, n).swapaxes(1, 2).reshape(hb, wb, n * n)


def _walls_and_bodies(name: str) -> tuple[float, float, list[int]]:
    """Over a sample of a layout's cameras at 320x180: the wall's local contrast (the spread
    within 6x6 blocks that are all wall: the shading is smooth, the texture is not), its mean
    level, and how many other cameras' bodies each camera sees drawn where they are."""
    cfg = layout(name, texture_size=512, width=320, height=180, exposure=0.0)
    scene = SynthScene(cfg)
    cams = scene.cameras()
    bodies = np.array([c.center - CAMERA_BEHIND * c.forward for c in cams])
    r = MeshRenderer(scene, cfg.width, cfg.height)
    r.set_frame(0)
    local, level, seen = [], [], []
    v, u = np.mgrid[0:cfg.height, 0:cfg.width]
    for cam in cams[:: max(1, len(cams) // 6)]:
        img, d = r.render(cam).astype(np.float64).mean(-1) / 255, r.render_depth(cam)
        world = (np.stack([(u + 0.5 - cam.cx) / cam.fx * d, (v + 0.5 - cam.cy) / cam.fy * d, d], -1) - cam.t) @ cam.R
        wall = (np.linalg.norm(world[..., :2], axis=-1) > cfg.backdrop_radius - 0.02) & (world[..., 2] > 0.2)
        local.append(_blocks(img)[_blocks(wall).all(-1)].std(-1).mean())
        level.append(img[wall].mean())
        uv, z = cam.project(bodies)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        depth = d[uv[inside, 1].astype(int), uv[inside, 0].astype(int)]
        seen.append(int((np.abs(depth - z[inside]) < 0.15).sum()))
    r.release()
    return float(np.mean(local)), float(np.mean(level)), seen


def test_stage_walls_are_faint_and_the_cameras_see_each_other() -> None:
    """In the rendered frames the stage's wall is light and nearly flat: a faint texture, as faint
    as a real dome's (the CMU Panoptic dome's walls measure 0.004-0.007 so at 320x180, mmpose demo
    frames, bench/real_rigs.py panoptic) and a fraction of the textured dome's; every camera sees
    other cameras' bodies."""
    stage, level, seen = _walls_and_bodies("dome-stage")
    textured, _, _ = _walls_and_bodies("dome24")
    assert 0.002 < stage < 0.008 and stage < 0.3 * textured, (stage, textured)
    assert level > 0.65 and min(seen) >= 3, (level, seen)  # the high ring sees few (as in dome24's test)
