"""Evaluation with a fake model (the documented model API) and a fake scene whose ground truth
is rendered from known Gaussians: the exact model must score PSNR inf / SSIM 1, a perturbed one
the numbers of a direct computation; bad input must fail with one-line errors and leave
previous outputs alone."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from atgs.cameras import Camera, look_at
from atgs.data.errors import DataError
from atgs.eval import metrics as M
from atgs.eval.evaluate import EvalConfig, EvalError, evaluate, image_frames
from atgs.gaussians import Gaussians
from atgs.render import rasterize_gaussians

W, H = 32, 24


def make_cameras(n: int = 3, w: int = W, h: int = H) -> list[Camera]:
    f = 28.0 * w / W
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
    cams = []
    for i in range(n):
        a = 2 * math.pi * i / n
        eye = np.array([3 * math.cos(a), 3 * math.sin(a), 0.8])
        cams.append(Camera(f"cam{i:02d}", w, h, K, look_at(eye, np.zeros(3))))
    return cams


def make_gaussians(seed: int = 0, n: int = 40) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    return Gaussians(
        means=torch.randn(n, 3, generator=g) * 0.35,
        quats=torch.randn(n, 4, generator=g),
        scales=torch.rand(n, 3, generator=g) * 0.12 + 0.04,
        opacities=torch.rand(n, generator=g) * 0.5 + 0.5,
        colors=torch.rand(n, 3, generator=g),
    )


def moving(g: Gaussians, frame: int) -> Gaussians:
    """The scene's motion: everything slides along x with time."""
    return replace(g, means=g.means + torch.tensor([0.06 * frame, 0.0, 0.0]))


def render(g: Gaussians, cam: Camera, background: tuple[float, float, float] | None = None) -> torch.Tensor:
    out = rasterize_gaussians(g, cam, background=None if background is None else torch.tensor(background),
                              backend="torch")
    return out.image.clamp(0, 1)


@dataclass
class FakeModel:
    """The model API evaluation uses (docs/ARCHITECTURE.md): cameras, num_frames, gaussians_at_frame."""

    base: Gaussians
    cameras: list[Camera]
    num_frames: int = 4
    fps: float = 10.0
    training: bool = False
    calls: list[int] = field(default_factory=list)
    mode_seen: list[bool] = field(default_factory=list)

    def gaussians_at_frame(self, frame: int) -> Gaussians:
        self.calls.append(frame)
        self.mode_seen.append(self.training)
        return moving(self.base, frame)

    def train(self, mode: bool = True) -> "FakeModel":
        self.training = mode
        return self


@dataclass
class FakeScene:
    """In-memory stand-in with the PreparedScene attributes evaluation reads."""

    truth: Gaussians
    cameras: list[Camera]
    test_indices: list[int]
    num_frames: int = 4
    fps: float = 10.0
    missing: set[tuple[int, int]] = field(default_factory=set)
    background: tuple[float, float, float] | None = None

    def image(self, cam_index: int, frame: int) -> np.ndarray:
        if (cam_index, frame) in self.missing:
            name = self.cameras[cam_index].name
            raise DataError(f"images/{name}/{frame:06d}.png: frame file missing; re-run atgs-prepare")
        return render(moving(self.truth, frame), self.cameras[cam_index], self.background).numpy()


def fast_cfg(**kw) -> EvalConfig:
    return EvalConfig(backend="torch", progress=False, lpips=False, **kw)


@pytest.fixture()
def setup():
    cams = make_cameras()
    truth = make_gaussians(0)
    return cams, truth, FakeScene(truth, cams, test_indices=[1, 2])


def test_exact_model_scores_perfectly_and_writes_outputs(setup, tmp_path: Path) -> None:
    cams, truth, scene = setup
    model = FakeModel(truth, cams, training=True)
    res = evaluate(model, scene, fast_cfg(images_per_camera=2), tmp_path / "eval")
    assert len(res.rows) == 2 * 4
    assert all(math.isinf(r["psnr"]) and r["ssim"] == pytest.approx(1.0, abs=1e-6) for r in res.rows)
    assert res.mean("dssim1") == pytest.approx(0.0, abs=1e-6) and res.mean("dssim_ms") == pytest.approx(0.0, abs=1e-6)
    assert res.mean("lpips") == "unavailable"
    # evaluation ran in eval mode and restored training mode
    assert model.mode_seen == [False] * 4 and model.training is True
    out = tmp_path / "eval"
    rows = list(csv.DictReader(open(out / "per_view.csv")))
    assert [(r["camera"], int(r["frame"])) for r in rows] == [(c, f) for f in range(4) for c in ("cam01", "cam02")]
    assert rows[0]["psnr"] == "inf" and rows[0]["lpips"] == "unavailable"
    summary = json.loads((out / "summary.json").read_text(), parse_constant=lambda c: pytest.fail(f"non-JSON {c}"))
    assert summary["mean"]["psnr"] == "inf" and summary["lpips"]["available"] is False
    assert set(summary["per_camera"]) == {"cam01", "cam02"}
    assert summary["settings"]["frames"] == [0, 1, 2, 3] and summary["settings"]["ms_ssim_levels"] == 2
    pngs = sorted(p.relative_to(out).as_posix() for p in out.rglob("*.png"))
    assert pngs == [f"images/{c}/{f:06d}.png" for c in ("cam01", "cam02") for f in (0, 3)]
    panel = np.asarray(Image.open(out / "images/cam01/000003.png"))
    assert panel.shape == (H, 3 * W, 3)
    assert np.array_equal(panel[:, :W], panel[:, W:2 * W])  # render == ground truth
    assert panel[:, 2 * W:].max() == 0  # no error
    assert not [p for p in tmp_path.iterdir() if p.name != "eval"]  # no temp dirs left


def test_perturbed_model_matches_direct_computation(setup, tmp_path: Path) -> None:
    cams, truth, scene = setup
    wrong = replace(truth, colors=(truth.colors * 0.8 + 0.1), means=truth.means + 0.02)
    model = FakeModel(wrong, cams)
    res = evaluate(model, scene, fast_cfg(frames=(0, 1, 3), every=2, cameras=("cam00", "cam02")), tmp_path / "e")
    assert [(r["camera"], r["frame"]) for r in res.rows] == [("cam00", 0), ("cam02", 0), ("cam00", 3), ("cam02", 3)]
    by_view = {(r["camera"], r["frame"]): r for r in csv.DictReader(open(tmp_path / "e" / "per_view.csv"))}
    psnrs = []
    for ci, name in ((0, "cam00"), (2, "cam02")):
        for f in (0, 3):
            r = render(moving(wrong, f), cams[ci]).double()
            gt = torch.from_numpy(scene.image(ci, f)).double()
            expect_psnr = 10 * math.log10(1.0 / float(((r - gt) ** 2).mean()))
            psnrs.append(expect_psnr)
            row = by_view[(name, str(f))]
            assert 10 < expect_psnr < 60
            assert float(row["psnr"]) == pytest.approx(expect_psnr, abs=1e-4)
            assert float(row["ssim"]) == pytest.approx(float(M.ssim(r, gt)), abs=1e-5)
            assert float(row["dssim2"]) == pytest.approx(float(M.dssim2(r, gt)), abs=1e-5)
            assert float(row["ms_ssim"]) == pytest.approx(float(M.ms_ssim(r, gt)), abs=1e-5)
    assert res.mean("psnr") == pytest.approx(np.mean(psnrs), abs=1e-4)
    cam2 = [p for (c, _), p in zip([(n, f) for n in ("cam00", "cam02") for f in (0, 3)], psnrs) if c == "cam02"]
    assert res.summary["per_camera"]["cam02"]["psnr"] == pytest.approx(np.mean(cam2), abs=1e-4)


def test_library_call_without_output_dir(setup) -> None:
    cams, truth, scene = setup
    res = evaluate(FakeModel(truth, cams), scene, fast_cfg(frames=(2,)), keep_renders=True)
    assert res.out_dir is None and len(res.rows) == 2
    assert np.allclose(res.renders[("cam01", 2)], scene.image(1, 2))


def test_renders_with_the_models_near_plane(setup) -> None:
    """A model's near plane culls the Gaussians nearer the (held-out) camera, as training did."""
    cams, truth, scene = setup
    model = FakeModel(truth, cams)
    model.near = 2.9  # the cameras stand ~3.1 from the scene's centre: some Gaussians are nearer
    res = evaluate(model, scene, fast_cfg(frames=(2,)), keep_renders=True)
    g, cam = moving(truth, 2), cams[1]
    want = rasterize_gaussians(g, cam, backend="torch", near=2.9).image.clamp(0, 1).numpy()
    assert np.allclose(res.renders[("cam01", 2)], want)
    assert not np.allclose(want, scene.image(1, 2), atol=1e-3)  # (the default near plane draws more)


@pytest.mark.parametrize("change,match", [
    ("pose", "differs between the checkpoint and the scene"),
    ("name", "not one of the checkpoint's cameras"),
    ("frames", "checkpoint has 5 frames but the scene has 4"),
    ("cameras", r"--cameras: \['nope'\] not in the scene"),
    ("range", r"--frames: \[7\] out of range \[0, 4\)"),
    ("missing", "cam02/000002.png: frame file missing"),
    ("no_test", "no test cameras"),
])
def test_bad_input_fails_cleanly_and_keeps_previous_output(setup, tmp_path: Path, change: str, match: str) -> None:
    cams, truth, scene = setup
    out = tmp_path / "eval"
    evaluate(FakeModel(truth, cams), scene, fast_cfg(frames=(0,), images_per_camera=0), out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    model, cfg = FakeModel(truth, cams), fast_cfg()
    if change == "pose":
        moved = cams[1].w2c.copy()
        moved[0, 3] += 0.1
        model.cameras = [cams[0], replace(cams[1], w2c=moved), cams[2]]
    elif change == "name":
        model.cameras = [replace(c, name=c.name.upper()) for c in cams]
    elif change == "frames":
        model.num_frames = 5
    elif change == "cameras":
        cfg = fast_cfg(cameras=("cam00", "nope"))
    elif change == "range":
        cfg = fast_cfg(frames=(1, 7))
    elif change == "missing":
        scene.missing = {(2, 2)}  # fails after several views were already written
    elif change == "no_test":
        scene.test_indices = []
    with pytest.raises(EvalError, match=match) as err:
        evaluate(model, scene, cfg, out)
    assert "\n" not in str(err.value)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["eval"]


def test_rescaled_cameras_agree(setup) -> None:
    cams, truth, scene = setup
    # a checkpoint trained at half resolution still evaluates against full-resolution data
    model = FakeModel(truth, [c.scaled(0.5) for c in cams])
    res = evaluate(model, scene, fast_cfg(frames=(1,)))
    assert all(math.isinf(r["psnr"]) for r in res.rows)


def test_image_frames_spacing() -> None:
    assert image_frames(list(range(10)), 3) == {0, 5, 9}  # 4.5 rounds up, as every evenly spaced choice
    assert image_frames([3, 5], 3) == {3, 5}
    assert image_frames([1, 2, 3], 0) == set()


def test_background_is_the_training_background(setup) -> None:
    cams, truth, _ = setup
    scene = FakeScene(truth, cams, [1], background=(1.0, 1.0, 1.0))  # trained over white
    model = FakeModel(truth, cams)
    white = evaluate(model, scene, fast_cfg(frames=(1,)), background=(1.0, 1.0, 1.0))
    assert math.isinf(white.mean("psnr")) and white.summary["settings"]["background"] == [1.0, 1.0, 1.0]
    black = evaluate(model, scene, fast_cfg(frames=(1,)))
    assert black.mean("psnr") < 20


def test_reduced_resolution_evaluation(setup) -> None:
    cams, truth, _ = setup
    big = make_cameras(w=64, h=48)
    scene = FakeScene(truth, big, [1])
    res = evaluate(FakeModel(truth, big), scene, fast_cfg(frames=(2,), resolution_scale=0.5), keep_renders=True)
    render_half = res.renders[("cam01", 2)]
    assert render_half.shape == (24, 32, 3)
    # ground truth: the full-resolution image, quantised and Lanczos-downsampled
    u8 = np.clip(np.round(scene.image(1, 2) * 255), 0, 255).astype(np.uint8)
    gt = np.asarray(Image.fromarray(u8).resize((32, 24), Image.Resampling.LANCZOS), np.float32) / 255
    mse = float(np.mean((render_half.astype(np.float64) - gt) ** 2))
    assert res.rows[0]["psnr"] == pytest.approx(10 * math.log10(1 / mse), abs=1e-4)
    assert 20 < res.rows[0]["psnr"] < 60  # close (same scene) but not identical (resampling)
    with pytest.raises(EvalError, match="resolution-scale"):
        evaluate(FakeModel(truth, big), scene, fast_cfg(resolution_scale=1.5))
