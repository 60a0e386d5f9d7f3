"""Nothing about a held-out camera enters training (issue 49): two runs whose scenes differ only in
the held-out camera's pose and images end in the same checkpoint, tensor for tensor, but for that
camera's own stored pose (metadata for evaluation). The held-out camera is moved into the content,
onto a decoded Gaussian, so a clearance around it (its housing, atgs.geometry.clearance) would cut
Gaussians that training sees; the run has every set-up step that reads cameras or images on
(random anchors carved by free space, the free-space loss, 3D smoothing, background and exposure
from the images, velocities from flow, densification, a periodic evaluation on the held-out camera)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from atgs.cameras import look_at
from atgs.checkpoint import read_checkpoint
from atgs.data.scene import MIN_BOUNDS_POINTS, MemoryScene
from atgs.train.scene_setup import model_from_scene
from atgs.train.trainer import Trainer
from builders import growing_tiny_config, make_toy_scene, textured_copy

STEPS = 8


def _configs():
    m, t = growing_tiny_config(STEPS)
    m.random_anchors, m.smoothing_3d = 64, 0.2
    t.lambda_free_space, t.lambda_ray_free_space, t.camera_exposure = 0.05, 0.1, "on"
    t.cameras_per_frame = 2
    t.eval_every, t.eval_max_frames = 4, 1  # a periodic evaluation on the held-out camera mid-run
    return m, t


@pytest.fixture(scope="module")
def scenes() -> tuple[MemoryScene, MemoryScene, int]:
    """(the toy scene in noise images (no uniform backdrop: the background is a map by direction),
    the same with its held-out camera moved onto a decoded Gaussian and showing other noise, the
    held-out camera's index)."""
    a = textured_copy(make_toy_scene(num_frames=4, num_cameras=5, width=32, height=24, keyframes=2))
    held = a.test_indices[0]
    m, t = _configs()
    means = model_from_scene(a, m, a.train_indices, t.seed).gaussians_at_frame(0).means.double().numpy()
    eye = means[np.argmin(np.linalg.norm(means, axis=1))]  # the Gaussian nearest the middle of the content
    old = a.cameras[held]
    moved = replace(old, w2c=look_at(eye, eye + np.array([1.0, 0.3, 0.0])))
    rng = np.random.default_rng(7)
    frames = dict(a.frames)
    for f in range(a.num_frames):
        frames[(held, f)] = rng.integers(0, 256, (old.height, old.width, 3), dtype=np.uint8)
    b = replace(a, cameras=[moved if i == held else c for i, c in enumerate(a.cameras)], frames=frames)
    return a, b, held


def _train(scene: MemoryScene, out) -> dict:
    m, t = _configs()
    Trainer(scene, m, t, out, progress=False).run_steps(progress=False)
    return read_checkpoint(out / "ckpt.pt")


def _leaves(tree, path=()):
    """(path, value) of every leaf of nested dicts, lists and tuples."""
    if isinstance(tree, dict):
        for k in sorted(tree, key=str):
            yield from _leaves(tree[k], path + (k,))
    elif isinstance(tree, (list, tuple)):
        for i, v in enumerate(tree):
            yield from _leaves(v, path + (i,))
    else:
        yield path, tree


def _same(x, y) -> bool:
    if isinstance(x, torch.Tensor) or isinstance(y, torch.Tensor):
        return (isinstance(x, torch.Tensor) and isinstance(y, torch.Tensor) and x.dtype == y.dtype
                and x.shape == y.shape and torch.equal(x, y))
    if isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y):
        return True
    return type(x) is type(y) and x == y


def test_moving_the_held_out_camera_changes_no_trained_value(scenes, tmp_path):
    a, b, held = scenes
    ca, cb = _train(a, tmp_path / "a"), _train(b, tmp_path / "b")
    assert ca["step"] == cb["step"] == STEPS
    assert ca["cameras"][held] != cb["cameras"][held]  # the held-out pose is stored, as metadata ...
    metadata = {("cameras", held), ("data_dir",), ("run_id",)}  # (run_id: each run its own)
    la, lb = dict(_leaves(ca)), dict(_leaves(cb))
    assert la.keys() == lb.keys()
    differ = [p for p in la if not any(p[:len(m)] == m for m in metadata) and not _same(la[p], lb[p])]
    assert not differ, f"what the held-out camera changed: {differ[:10]}"  # ... and nothing else
    assert sum(isinstance(v, torch.Tensor) for v in la.values()) > 40  # model, optimizers, sampler, exposure
    assert ca["trainer"]["exposure"] is not None and ca["environment"] is not None


def _prepared(scene: MemoryScene, root, points: str) -> tuple[dict, bytes, bytes | None]:
    """atgs-prepare of ``scene`` (an EasyVolcap folder, its held-out cameras given): (scene.json,
    points.ply, motion_points.ply or None). ``points`` "dense": stereo, a fill of every camera,
    extension and motion points (coarse: ~3 s); "none": no stereo, fill or motion points, so the
    tiny images' SIFT leaves too few points for bounds, which then come from the cameras (~1 s)."""
    import json

    from atgs.data.moving_points import MotionPointsConfig
    from atgs.data.mvs import FillConfig, StereoConfig
    from atgs.data.prepare import PrepareConfig, prepare
    from layouts import write_easyvolcap_layout

    src = write_easyvolcap_layout(root / "src", scene.cameras, lambda ci, f: scene.frames[(ci, f)], scene.num_frames)
    kw = (dict(stereo=StereoConfig(long_side=32), fill=FillConfig(below=1.0, points=2000),
               motion=MotionPointsConfig(per_interval=2, resolution=16, subdivide=1, long_side=32))
          if points == "dense" else
          dict(stereo=StereoConfig(enabled=False), fill=FillConfig(enabled=False),
               motion=MotionPointsConfig(enabled=False)))
    out = prepare(PrepareConfig(src=src, out=root / "prepared", keyframes=2, test_cams=tuple(scene.test_cameras),
                                progress=False, **kw))
    motion = out / "motion_points.ply"
    return (json.loads((out / "scene.json").read_text()), (out / "points.ply").read_bytes(),
            motion.read_bytes() if motion.is_file() else None)


@pytest.mark.parametrize("points", ["dense", "none"])
def test_moving_the_held_out_camera_changes_no_prepared_point(scenes, tmp_path, points):
    """atgs-prepare: the keyframe points (SIFT, stereo, fill, extension), the motion points and the
    bounds (from the points, or from the cameras when there are too few) come from the training
    cameras alone."""
    a, b, held = scenes
    (ja, pa, ma), (jb, pb, mb) = _prepared(a, tmp_path / "a", points), _prepared(b, tmp_path / "b", points)
    assert ja["cameras"][held] != jb["cameras"][held]
    assert pa == pb and ma == mb
    for key in ("bounds", "keyframe_points", "motion_points", "keyframes", "test_cameras"):
        assert ja[key] == jb[key], key
    counts = ja["keyframe_points"]
    if points == "dense":  # (not vacuous)
        assert all(sum(counts[k]) > 0 for k in ("stereo", "fill", "extend")) and sum(ja["motion_points"]["points"])
    else:
        assert sum(sum(n) for n in counts.values()) < MIN_BOUNDS_POINTS
    train = [c["name"] for i, c in enumerate(ja["cameras"]) if i != held]
    ca, cb = ja["coverage"], jb["coverage"]  # (the held-out camera's own coverage is a report of it)
    for x, y in ((ca, cb), (ca["views_per_pixel"], cb["views_per_pixel"])):
        assert x["mean"] == y["mean"] and all(x["per_camera"][n] == y["per_camera"][n] for n in train)
