"""CPU multi-view stereo, fusion, the fallback fill and coverage, against independent references:
an analytic ray caster of a solid-textured plane and box (exact depth), slow per-pixel
implementations, and brute force."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from atgs.cameras import Camera, look_at
from atgs.data.colmap_ops import ColmapOptions
from atgs.data.keyframe_points import keyframe_points
from atgs.data.mvs import FillConfig, StereoConfig, stereo_points
from atgs.data.mvs.fill import frustum_fill
from atgs.data.mvs.fusion import fuse_depth_maps, fuse_reference
from atgs.data.mvs.patchmatch import DepthMap, PlaneCost, patchmatch, patchmatch_cost_reference, random_normals
from atgs.data.mvs.views import depth_ranges, make_view
from atgs.data.scene import MemoryScene, write_prepared_scene
from atgs.geometry.coverage import coverage_mask, coverage_mask_reference, point_spacing, scene_coverage
from atgs.geometry.seen_space import fallback_points

W, H = 96, 72
BOX = (np.array([-0.45, -0.35, 0.0]), np.array([0.45, 0.35, 0.7]))
GROUND = 2.4  # half side of the ground square


# --- an independent renderer: analytic ray casting of a solid-textured ground plane and box ---------

def _noise(X: np.ndarray, seed: int = 0, cell: float = 0.07) -> np.ndarray:
    """Solid texture: RGB value noise on a lattice (trilinear), the same from every camera."""
    rng = np.random.default_rng(seed)
    lat = rng.random((96, 96, 96, 3))
    g = X / cell + 48.0
    i = np.clip(np.floor(g).astype(int), 0, 94)
    f = np.clip(g - i, 0, 1)
    out = 0
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = (f[:, 0] if dx else 1 - f[:, 0]) * (f[:, 1] if dy else 1 - f[:, 1]) * (f[:, 2] if dz else 1 - f[:, 2])
                out = out + w[:, None] * lat[i[:, 0] + dx, i[:, 1] + dy, i[:, 2] + dz]
    return out


def raycast(cam: Camera, box: bool = True, textured: bool = True, ss: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """(H,W,3) uint8 image (supersampled ss x ss) and (H,W) exact depth at pixel centers of the
    ground square |x|, |y| <= GROUND at z = 0 (and the box), 0 where nothing is hit."""
    def cast(u, v):
        d = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1).reshape(-1, 3) @ cam.R
        o = cam.center
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(d[:, 2] < 0, -o[2] / d[:, 2], np.inf)  # depth along the optical axis: d has z_cam = 1
            g = o + d * np.where(np.isfinite(t), t, 0)[:, None]
            t = np.where(np.abs(g[:, :2]).max(1) <= GROUND, t, np.inf)  # a square of ground
            if box:
                t0, t1 = (BOX[0] - o) / d, (BOX[1] - o) / d
                tn, tf = np.minimum(t0, t1).max(1), np.maximum(t0, t1).min(1)
                t = np.where((tn <= tf) & (tn > 0) & (tn < t), tn, t)
        X = o + d * np.where(np.isfinite(t), t, 0)[:, None]
        col = _noise(X) if textured else np.full((len(X), 3), 0.5)
        col[~np.isfinite(t)] = 0.0
        return col, np.where(np.isfinite(t), t, 0.0)

    vv, uu = np.mgrid[0:cam.height * ss, 0:cam.width * ss]
    col, _ = cast((uu + 0.5) / ss, (vv + 0.5) / ss)
    img = col.reshape(cam.height, ss, cam.width, ss, 3).mean((1, 3))
    vv, uu = np.mgrid[0:cam.height, 0:cam.width]
    _, depth = cast(uu + 0.5, vv + 0.5)
    return (np.clip(img, 0, 1) * 255).round().astype(np.uint8), depth.reshape(cam.height, cam.width)


def ring(n: int, radius: float = 2.6, height: float = 1.6, arc_deg: float = 360.0, w: int = W, h: int = H) -> list[Camera]:
    f = 0.8 * w
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
    cams = []
    for i in range(n):
        a = np.radians(arc_deg) * (i / n if arc_deg >= 360 else i / max(1, n - 1)) - np.pi / 2
        eye = np.array([radius * np.cos(a), radius * np.sin(a), height + 0.2 * (i % 2)])
        cams.append(Camera(f"cam{i:02d}", w, h, K, look_at(eye, np.array([0.0, 0.0, 0.3]))))
    return cams


def surface_distance(X: np.ndarray, box: bool = True) -> np.ndarray:
    d = np.abs(X[:, 2])
    if box:
        q = np.abs(X - (BOX[0] + BOX[1]) / 2) - (BOX[1] - BOX[0]) / 2
        db = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0)
        d = np.minimum(d, np.abs(db))
    return d


@pytest.fixture(scope="module")
def rig():
    cams = ring(8, arc_deg=150.0)
    rendered = [raycast(c) for c in cams]
    return cams, [r[0] for r in rendered], [r[1] for r in rendered]


CFG = StereoConfig(threads=1)


# --- PatchMatch ----------------------------------------------------------------------------------

def test_plane_cost_matches_the_per_sample_reference(rig) -> None:
    cams, imgs, _ = rig
    views = [make_view(i, c, 400) for i, c in zip(imgs, cams)]
    ref, srcs = views[3], [views[2], views[4], views[5]]
    pc = PlaneCost(ref, srcs, StereoConfig(window=5, window_step=2, top_k=2))
    gen = torch.Generator().manual_seed(1)
    pix = [(10, 12), (40, 30), (70, 50), (30, 60), (85, 8)]
    idx = torch.tensor([y * W + x for x, y in pix])
    inv = 0.2 + 0.4 * torch.rand(len(pix), generator=gen)
    normal = random_normals(pc.ray[idx], gen)
    fast = pc(idx, inv, normal).numpy()
    slow = [patchmatch_cost_reference(ref, srcs, p, float(i), n.numpy(), 5, 2, 2) for p, i, n in zip(pix, inv, normal)]
    np.testing.assert_allclose(fast, slow, atol=2e-3)
    assert np.ptp(slow) > 0.1  # the planes differ in cost: the comparison is not vacuous


def _depth_accuracy(dm: DepthMap, truth: np.ndarray) -> tuple[float, float, float]:
    """Share of the surface pixels with a depth; of those, the share within 2% and the median error."""
    d = dm.depth.numpy()
    ok = (d > 0) & (truth > 0)
    rel = np.abs(d[ok] - truth[ok]) / truth[ok]
    return float(ok.sum() / (truth > 0).sum()), float(np.mean(rel < 0.02)), float(np.median(rel))


@pytest.mark.parametrize("box", [False, True], ids=["plane", "box"])
def test_depth_of_a_textured_plane_and_box_matches_the_analytic_depth(box) -> None:
    cams = ring(6, arc_deg=100.0)
    rendered = [raycast(c, box=box) for c in cams]
    views = [make_view(r[0], c, 400) for r, c in zip(rendered, cams)]
    ref = 2
    pts = np.concatenate([np.random.default_rng(0).uniform(-1.5, 1.5, (200, 3)) * [1, 1, 0]])  # seeds on the ground
    near, far = depth_ranges([v.cam for v in views], pts)[ref]
    dm = patchmatch(views[ref], [views[j] for j in (1, 3, 0, 4)], near, far, CFG)
    valid, good, median = _depth_accuracy(dm, rendered[ref][1])
    assert valid > 0.9 and good > 0.8 and median < 0.005, (valid, good, median)


def test_stereo_points_lie_on_the_surfaces(rig) -> None:
    cams, imgs, _ = rig
    res = stereo_points(imgs, cams, CFG)
    extent = 2 * 2.6  # the camera ring's diameter
    d = surface_distance(res.points)
    # the tail is edge fattening where the ground ends against the empty background (~10% at 96x72)
    assert len(res.points) > 1000 and np.median(d) < 0.002 * extent and np.mean(d < 0.01 * extent) > 0.8, (
        len(res.points), np.median(d) / extent, np.mean(d < 0.01 * extent))
    inner = np.abs(res.points[:, :2]).max(1) < GROUND - 0.3
    assert np.mean(d[inner] < 0.01 * extent) > 0.95, np.mean(d[inner] < 0.01 * extent)


# --- fusion --------------------------------------------------------------------------------------

def _true_maps(rig, scale: dict | None = None) -> tuple[list, list]:
    cams, imgs, depths = rig
    views = [make_view(i, c, 400) for i, c in zip(imgs, cams)]
    maps = []
    for k, d in enumerate(depths):
        d = torch.from_numpy(d).float() * (scale or {}).get(k, 1.0)
        maps.append(DepthMap(d, (d > 0).float()))
    return views, maps


def test_fusion_keeps_true_depths_and_rejects_an_inconsistent_map(rig) -> None:
    views, maps = _true_maps(rig)
    n = len(views)
    only0 = [[j for j in range(n) if j != 0] if r == 0 else [] for r in range(n)]  # points of camera 0 only
    pts, _ = fuse_depth_maps(views, maps, only0, CFG)
    assert len(pts) > 0.75 * int((maps[0].depth > 0).sum()) and surface_distance(pts).max() < 0.01
    left = lambda p: views[0].cam.project(p)[0][:, 0] < W // 2  # noqa: E731
    wrong = [DepthMap(maps[0].depth * 1.05, maps[0].confidence)] + maps[1:]  # camera 0 is 5% off
    pts_wrong, _ = fuse_depth_maps(views, wrong, only0, CFG)
    assert len(pts_wrong) < 0.05 * len(pts)
    half = maps[0].depth.clone()
    half[:, : W // 2] *= 1.05  # only the left half is wrong: the right half survives
    pts_half, _ = fuse_depth_maps(views, [DepthMap(half, maps[0].confidence)] + maps[1:], only0, CFG)
    assert left(pts_half).sum() < 0.05 * left(pts).sum() and (~left(pts_half)).sum() > 0.95 * (~left(pts)).sum()
    # the few wrong depths that pass land on another true surface (seen there by the other cameras)
    assert surface_distance(pts_half).max() < 0.02


def test_fusion_matches_the_per_pixel_reference(rig) -> None:
    views, maps = _true_maps(rig, scale={2: 1.004})  # one map slightly off: some agreements fail
    small = [make_view((v.rgb.numpy() * 255).astype(np.uint8), v.cam, 24) for v in views]
    sm = [DepthMap(torch.nn.functional.interpolate(m.depth[None, None], size=s.gray.shape, mode="nearest")[0, 0],
                   torch.ones(s.gray.shape)) for m, s in zip(maps, small)]
    checks = [[j for j in range(len(views)) if j != r] for r in range(len(views))]
    cfg = StereoConfig(reproj_px=0.5, rel_depth=0.005)
    fast, fast_c = fuse_depth_maps(small, sm, checks, cfg)
    slow, slow_c = fuse_reference(small, sm, checks, cfg)
    assert len(fast) == len(slow) > 20
    np.testing.assert_allclose(fast, slow, atol=1e-6)
    np.testing.assert_allclose(fast_c, slow_c, atol=1e-5)


# --- coverage ------------------------------------------------------------------------------------

def test_coverage_mask_matches_brute_force() -> None:
    cam = ring(1, w=60, h=40)[0]
    rng = np.random.default_rng(3)
    pts = rng.uniform([-1.5, -1.5, 0], [1.5, 1.5, 1.0], (300, 3))
    for spacing in (0.01, 0.05, 0.2):
        fast = coverage_mask(cam, pts, spacing)
        slow = coverage_mask_reference(cam, pts, spacing)
        assert np.array_equal(fast, slow) and 0 < slow.mean() < 1
    assert point_spacing(np.array([[0, 0, 0], [0, 0, 1.0], [0, 0, 3.0]])) == pytest.approx(1.0)


def test_scene_coverage_reports_every_camera_and_the_test_cameras(rig) -> None:
    cams, _, depths = rig
    c = cams[0]
    v, u = np.nonzero(depths[0] > 0)
    z = depths[0][v, u]
    X = (np.stack([(u + 0.5 - c.cx) / c.fx * z, (v + 0.5 - c.cy) / c.fy * z, z], 1) - c.t) @ c.R
    cov = scene_coverage(cams, X, np.zeros(len(X), np.int64), 1, test_cameras=["cam07"])
    assert cov["per_camera"]["cam00"] > 0.95 * np.mean(depths[0] > 0)  # its own depth covers camera 0's surfaces
    assert set(cov["test_cameras"]) == {"cam07"} and cov["per_camera"]["cam07"] < cov["per_camera"]["cam00"]


# --- the fallback start --------------------------------------------------------------------------

def _prepared(tmp_path, cams, imgs):
    root = write_prepared_scene(tmp_path / "scene", MemoryScene(cams, 1), lambda ci, f: imgs[ci])
    return root, (tmp_path / "work")


def _seen_by(cams, X) -> np.ndarray:
    n = np.zeros(len(X), int)
    for c in cams:
        uv, z = c.project(X)
        n += (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < c.width) & (uv[:, 1] >= 0) & (uv[:, 1] < c.height)
    return n


def test_textureless_images_take_the_fallback(tmp_path) -> None:
    cams = ring(4, w=64, h=48)
    imgs = [raycast(c, textured=False, ss=1)[0] for c in cams]
    root, work = _prepared(tmp_path, cams, imgs)
    kp = keyframe_points(root, cams, [], [0], ".png", work, ColmapOptions(), CFG, FillConfig(), progress=False)
    assert kp.counts["stereo"] == [0] and kp.counts["sift"] == [0] and kp.counts["fill"][0] > 1000
    assert np.all(_seen_by(cams, kp.points) >= 2) and kp.coverage["mean"] == 0.0


def test_two_camera_rig_takes_the_fallback(tmp_path) -> None:
    cams = ring(4, w=64, h=48)[:2]  # two cameras 90 degrees apart, as in a sparse lab capture
    imgs = [raycast(c, ss=1)[0] for c in cams]
    root, work = _prepared(tmp_path, cams, imgs)
    kp = keyframe_points(root, cams, [], [0], ".png", work, ColmapOptions(), CFG, FillConfig(), progress=False)
    assert kp.counts["fill"][0] > 500 and np.all(_seen_by(cams, kp.points) == 2)


def test_fill_is_inside_the_common_frusta_through_the_given_pixels(rig) -> None:
    cams, imgs, _ = rig
    ranges = depth_ranges(cams, None)
    masks = [None] * len(cams)
    masks[0] = np.zeros((H, W), bool)
    masks[0][:, : W // 4] = True  # rays through the left quarter of camera 0 only
    pts, cols = frustum_fill(cams, ranges, FillConfig(points=3000), images=imgs, masks=masks)
    assert len(pts) > 500 and np.all(_seen_by(cams, pts) >= 2) and cols.shape == pts.shape
    uv, z = cams[0].project(pts)
    assert np.all(uv[:, 0] <= W / 4 + 1e-6) and np.all((z >= ranges[0][0]) & (z <= ranges[0][1]))
    # colours are the mean of the pixels the point projects to in the cameras that see it
    p, c = pts[:1], []
    for cam, img in zip(cams, imgs):
        q, zz = cam.project(p)
        if ranges[cams.index(cam)][0] <= zz[0] <= ranges[cams.index(cam)][1] and 0 <= q[0, 0] < W and 0 <= q[0, 1] < H:
            c.append(img[int(q[0, 1]), int(q[0, 0])] / 255.0)
    np.testing.assert_allclose(cols[0], np.mean(c, 0), atol=1e-6)


def test_fallback_points_for_a_scene_without_any(rig) -> None:
    cams = rig[0]
    pts = fallback_points(cams, 2000)
    assert 500 < len(pts) <= 2000 and np.all(_seen_by(cams, pts) >= 2)
    apart = [Camera("a", W, H, cams[0].K, look_at(np.zeros(3), np.array([1.0, 0, 0]))),
             Camera("b", W, H, cams[0].K, look_at(np.array([0, 0.5, 0]), np.array([-1.0, 0.5, 0])))]
    assert len(fallback_points(apart, 500)) > 0  # nothing seen twice: falls back to single views


# --- degenerate rigs: a one-line error or the fallback, never a traceback ------------------------

def _rig_source(tmp_path, cams) -> str:
    from layouts import write_colmap_frames_layout

    imgs = [raycast(c, ss=1)[0] for c in cams]
    return str(write_colmap_frames_layout(tmp_path / "src", cams, lambda ci, f: imgs[ci], 1))


def _look(eye, target, name) -> Camera:
    f = 0.8 * 64
    return Camera(name, 64, 48, np.array([[f, 0, 32], [0, f, 24], [0, 0, 1]]), look_at(np.asarray(eye, float), np.asarray(target, float)))


@pytest.mark.parametrize("case", ["one camera", "coincident cameras", "nothing in common"])
def test_degenerate_rigs_give_a_one_line_error(tmp_path, capsys, case) -> None:
    from atgs.cli.prepare import main as prepare_main

    eye = np.array([2.6, 0.0, 1.6])
    cams = {"one camera": [_look(eye, [0, 0, 0.3], "cam00")],
            "coincident cameras": [_look(eye, [0, y, 0.3], f"cam{i:02d}") for i, y in enumerate((-0.6, 0.0, 0.6))],
            "nothing in common": [_look(eye, [0, 0, 0.3], "cam00"), _look(eye + [0, 0.1, 0], [6, 0.1, 1.6], "cam01")]}[case]
    code = prepare_main([_rig_source(tmp_path, cams), "--out", str(tmp_path / "out"), "--keyframes", "1", "--test-cams"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and not (tmp_path / "out").exists()
    assert err[-1].startswith("atgs-prepare: error: ") and "Traceback" not in "".join(err), err
    assert ".tmp" not in err[-1] and str(tmp_path / "src") in err[-1]  # names the capture, not a temp folder
    assert {"one camera": "at least 2 cameras", "coincident cameras": "same position",
            "nothing in common": "no two cameras see a common region"}[case] in err[-1]


def test_held_out_cameras_never_feed_the_keyframe_points(tmp_path) -> None:
    """Three cameras, cam00 held out: the points are the same whatever cam00's image shows (its
    pixels would otherwise leak into the held-out score)."""
    cams = ring(4, w=64, h=48)[:3]
    imgs = [raycast(c, ss=1)[0] for c in cams]
    noise = np.random.default_rng(0).integers(0, 256, imgs[0].shape, dtype=np.uint8)
    runs = []
    for name, first in (("real", imgs[0]), ("noise", noise)):
        root = write_prepared_scene(tmp_path / name, MemoryScene(cams, 1), lambda ci, f: first if ci == 0 else imgs[ci])
        runs.append(keyframe_points(root, cams, [cams[0].name], [0], ".png", tmp_path / f"work-{name}",
                                    ColmapOptions(), CFG, FillConfig(), progress=False))
    assert len(runs[0].points) > 100
    np.testing.assert_array_equal(runs[0].points, runs[1].points)
    np.testing.assert_array_equal(runs[0].colors, runs[1].colors)


def test_a_two_camera_capture_holds_out_none_by_default(tmp_path, capsys) -> None:
    """The convention (hold out cam00) would leave one camera to train on: none is held out, with
    a note. Asking for it explicitly is a one-line error that writes nothing."""
    from atgs.cli.prepare import main as prepare_main
    from atgs.data.scene import PreparedScene

    eye = np.array([2.6, 0.0, 1.6])
    cams = [_look(eye, [0, 0, 0.3], "cam00"), _look([0.0, 2.6, 1.6], [0, 0, 0.3], "cam01")]
    src = _rig_source(tmp_path, cams)
    assert prepare_main([src, "--out", str(tmp_path / "held"), "--keyframes", "1", "--test-cams", "cam00"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(f"atgs-prepare: error: {src}: --test-cams cam00 holds out all but 1") and "cam01" in err[-1]
    assert not (tmp_path / "held").exists()
    assert prepare_main([src, "--out", str(tmp_path / "out"), "--keyframes", "1", "--no-progress"]) == 0
    assert "none held out" in capsys.readouterr().err
    scene = PreparedScene.load(tmp_path / "out")
    assert scene.test_cameras == [] and len(scene.train_indices) == 2
    # atgs-train's closing line says its figure is from a training view, not a held-out one
    from atgs.cli.train import main as train_main

    assert train_main(["--data", str(tmp_path / "out"), "--out", str(tmp_path / "run"), "tiny",
                       "--train.iterations", "2", "--no-progress"]) == 0
    done = [ln for ln in capsys.readouterr().out.splitlines() if "done," in ln]
    assert done and "training-view (no held-out camera) PSNR" in done[-1] and "test PSNR" not in done[-1]
    # atgs-eval has no held-out camera to default to: one line naming the scene and --cameras
    from atgs.cli.evaluate import main as eval_main

    assert eval_main([str(tmp_path / "run" / "ckpt.pt")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(f"atgs-eval: error: {tmp_path / 'out'}: no test cameras") and "--cameras" in err[-1]


def test_an_empty_point_cloud_trains(tmp_path, capsys) -> None:
    from atgs.data.scene import PreparedScene
    from atgs.train.config import preset
    from builders import make_toy_scene
    from atgs.train.trainer import Trainer

    toy = make_toy_scene(num_frames=4, num_cameras=4, width=40, height=32, keyframes=2)
    root = write_prepared_scene(tmp_path / "empty", MemoryScene(toy.cameras, toy.num_frames, keyframes=toy.keyframes,
                                                                test_cameras=toy.test_cameras), toy.image_uint8)
    scene = PreparedScene.load(root)
    assert len(scene.points) == 0 and np.all(scene.bounds[1] > scene.bounds[0])
    m, t = preset("tiny")
    t.iterations, t.eval_max_frames = 6, 1
    tr = Trainer(scene, m, t, tmp_path / "run")
    assert "points.ply is empty" in capsys.readouterr().err and tr.model.num_anchors > 10
    rows = [tr.train_step() for _ in range(6)]
    assert all(np.isfinite(r.loss) for r in rows) and any(r.gaussians > 0 for r in rows)


@pytest.mark.parametrize("case", ["one camera", "coincident cameras", "nothing in common"])
def test_the_model_starts_without_points_on_degenerate_rigs(case, capsys) -> None:
    from atgs.model.atgs_model import ATGSModel
    from atgs.train.config import preset

    eye = np.array([2.6, 0.0, 1.6])
    cams = {"one camera": [_look(eye, [0, 0, 0.3], "a")],
            "coincident cameras": [_look(eye, [0, y, 0.3], f"c{i}") for i, y in enumerate((-0.6, 0.0, 0.6))],
            "nothing in common": [_look(eye, [0, 0, 0.3], "a"), _look(eye + [0, 0.1, 0], [6, 0.1, 1.6], "b")]}[case]
    m, _ = preset("tiny")
    model = ATGSModel.from_points(m, torch.zeros(0, 3), torch.zeros(0, dtype=torch.long), [0, 3], 4, 30.0, cams, cams)
    mu = model.anchor_mu.numpy()
    assert model.num_anchors > 100 and np.isfinite(mu).all() and np.ptp(mu, axis=0).max() > 0.1
    # anchors are voxel averages of the fill: a few at the frustum edges fall just outside
    assert np.mean(_seen_by(cams, mu.astype(np.float64)) >= 1) > 0.95 and "points.ply is empty" in capsys.readouterr().err


# --- surface extension into uncovered pixels (atgs.data.mvs.extend) ----------------------------

def _down_camera() -> Camera:
    """A camera 2 m above the ground looking straight down: the ground is fronto-parallel, its
    depth is 2 at every pixel, so extending it at the neighbours' depth is exact."""
    f = 0.8 * W
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])
    return Camera("down", W, H, K, look_at(np.array([0.0, 0.0, 2.0]), np.zeros(3), up=np.array([0.0, 1.0, 0.0])))


def _ground_points(cam: Camera, first_row: int) -> np.ndarray:
    """Ground points (z = 0) through every pixel center of ``cam`` from row ``first_row`` down."""
    vv, uu = np.mgrid[first_row:cam.height, 0:cam.width]
    d = np.stack([(uu + 0.5 - cam.cx) / cam.fx, (vv + 0.5 - cam.cy) / cam.fy, np.ones(uu.shape)], -1).reshape(-1, 3)
    pc = d * 2.0  # depth 2 everywhere
    return (pc - cam.t) @ cam.R


def test_extension_continues_a_fronto_parallel_plane_into_the_uncovered_rows() -> None:
    from atgs.data.mvs.extend import extend_surfaces

    cam = _down_camera()
    img, depth = raycast(cam, box=False)
    assert np.allclose(depth, 2.0), "the analytic ground is at depth 2"
    pts = _ground_points(cam, first_row=30)  # rows 0-29 uncovered
    sp = point_spacing(pts)
    ext, cols = extend_surfaces([cam], [img], pts, sp, long_side=W, reach=0.1, max_points=100_000)
    assert len(ext) > 50
    np.testing.assert_allclose(ext[:, 2], 0.0, atol=1e-9)  # on the plane: the depth is exact
    uv, z = cam.project(ext)
    assert np.all(uv[:, 1] < 30), "only uncovered pixels get points"
    covered = coverage_mask(cam, pts, sp)
    first_covered = int(np.nonzero(covered.any(1))[0][0])
    reach_px = 0.1 * W
    assert uv[:, 1].min() >= first_covered - reach_px - 3, "no further than the reach (+ the points' gaps)"
    assert uv[:, 1].min() < first_covered - 0.5 * reach_px, "the extension reaches out"
    # colours come from the image at those pixels
    xi, yi = uv[:, 0].astype(int), uv[:, 1].astype(int)
    np.testing.assert_allclose(cols, img[yi, xi] / 255.0, atol=1 / 255)


def test_extension_adds_nothing_to_a_covered_camera_and_respects_its_caps() -> None:
    from atgs.data.mvs.extend import extend_surfaces

    cam = _down_camera()
    img, _ = raycast(cam, box=False)
    full = _ground_points(cam, first_row=0)
    ext, _ = extend_surfaces([cam], [img], full, point_spacing(full), long_side=W, reach=0.2, max_points=1000)
    assert len(ext) == 0
    part = _ground_points(cam, first_row=30)
    for reach, cap in ((0.0, 1000), (0.2, 0)):
        ext, _ = extend_surfaces([cam], [img], part, point_spacing(part), long_side=W, reach=reach, max_points=cap)
        assert len(ext) == 0
    ext, _ = extend_surfaces([cam], [img], part, point_spacing(part), long_side=W, reach=0.2, max_points=7)
    assert len(ext) == 7


def test_grow_depth_fills_ring_by_ring_and_keeps_known_depths() -> None:
    from atgs.data.mvs.extend import grow_depth

    d = np.full((9, 9), np.nan)
    d[4, 4] = 3.0
    d[0, 0] = 1.0
    g = grow_depth(d, 2)
    assert g[4, 4] == 3.0 and g[0, 0] == 1.0
    assert g[4, 6] == 3.0 and g[2, 4] == 3.0 and np.isnan(g[4, 7]), "two rings, 4-neighbour distance"
    assert np.isnan(grow_depth(d, 0)[4, 5])
    assert not np.isnan(grow_depth(d, 20)).any()


def test_stereo_thread_count_caps_at_torchs_threads() -> None:
    from atgs.data.mvs.stereo import idle_cores, stereo_thread_count

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        assert stereo_thread_count(1) == 1 and stereo_thread_count(8) == 2
        assert stereo_thread_count(0) == min(2, idle_cores())
    finally:
        torch.set_num_threads(before)
