"""LPIPS: found only from weights on disk, reported unavailable otherwise, and (with stand-in
weights of the real shapes) equal to a layer-by-layer reference of the LPIPS v0.1 formula."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from atgs.eval.lpips import ALEXNET_FILE, LPIPS_CHANNELS, find_lpips_weights, load_lpips

# torchvision AlexNet conv shapes by `features` index
CONV_SHAPES = {0: (64, 3, 11, 11), 3: (192, 64, 5, 5), 6: (384, 192, 3, 3), 8: (256, 384, 3, 3), 10: (256, 256, 3, 3)}


def write_standin_weights(tmp: Path, seed: int = 0) -> tuple[Path, Path]:
    g = torch.Generator().manual_seed(seed)
    backbone = {}
    for idx, shape in CONV_SHAPES.items():
        fan_in = shape[1] * shape[2] * shape[3]
        backbone[f"features.{idx}.weight"] = torch.randn(shape, generator=g) / fan_in**0.5
        backbone[f"features.{idx}.bias"] = torch.randn(shape[0], generator=g) * 0.1
    backbone["classifier.1.weight"] = torch.zeros(4, 4)  # extra keys of the real file are ignored
    linear = {f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1, generator=g) for k, c in enumerate(LPIPS_CHANNELS)}
    b, lin = tmp / ALEXNET_FILE, tmp / "alex.pth"
    torch.save(backbone, b)
    torch.save(linear, lin)
    return b, lin


def ref_lpips(x: np.ndarray, y: np.ndarray, backbone: dict, linear: dict) -> float:
    """LPIPS v0.1 written out step by step: scaling layer, AlexNet relu1..relu5, unit-normalise
    channels, squared difference, linear head, spatial mean, sum over layers."""
    shift = np.array([-0.030, -0.088, -0.188]).reshape(1, 3, 1, 1)
    scale = np.array([0.458, 0.448, 0.450]).reshape(1, 3, 1, 1)

    def feats(img: np.ndarray) -> list[np.ndarray]:
        h = torch.tensor(((2 * img.transpose(2, 0, 1)[None] - 1) - shift) / scale, dtype=torch.float32)
        out = []
        plan = [(0, 4, 2, False), (3, 1, 2, True), (6, 1, 1, True), (8, 1, 1, False), (10, 1, 1, False)]
        for idx, stride, pad, pool_first in plan:
            if pool_first:
                h = F.max_pool2d(h, 3, 2)
            h = torch.relu(F.conv2d(h, backbone[f"features.{idx}.weight"], backbone[f"features.{idx}.bias"],
                                    stride=stride, padding=pad))
            out.append(h[0].numpy().astype(np.float64))
        return out

    total = 0.0
    for k, (fa, fb) in enumerate(zip(feats(x), feats(y))):
        na = fa / (np.sqrt((fa**2).sum(0, keepdims=True)) + 1e-10)
        nb = fb / (np.sqrt((fb**2).sum(0, keepdims=True)) + 1e-10)
        w = linear[f"lin{k}.model.1.weight"].numpy().reshape(-1, 1, 1)
        total += float((w * (na - nb) ** 2).sum(0).mean())
    return total


def test_unavailable_without_weights(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "hub_home"))
    net, reason = load_lpips(linear=tmp_path / "none.pth")
    assert net is None
    assert str(tmp_path / "hub_home" / "hub" / "checkpoints" / ALEXNET_FILE) in reason
    assert "none.pth" in reason and "\n" not in reason
    found, _ = find_lpips_weights(linear=tmp_path / "none.pth")
    assert not found.available


def test_corrupt_weights_are_reported(tmp_path: Path) -> None:
    b, lin = write_standin_weights(tmp_path)
    lin.write_bytes(b"not a torch file")
    net, reason = load_lpips(b, lin)
    assert net is None and "unusable" in reason
    torch.save({"lin0.model.1.weight": torch.zeros(1, 3, 1, 1)}, lin)  # wrong shape
    net, reason = load_lpips(b, lin)
    assert net is None and "lin0.model.1.weight" in reason


def test_lpips_matches_reference_with_standin_weights(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    b, lin = write_standin_weights(tmp_path)
    # found through the torch hub cache like a real installation
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "th"))
    (tmp_path / "th" / "hub" / "checkpoints").mkdir(parents=True)
    (tmp_path / "th" / "hub" / "checkpoints" / ALEXNET_FILE).write_bytes(b.read_bytes())
    net, reason = load_lpips(linear=lin)
    assert net is not None, reason
    rng = np.random.default_rng(0)
    x = rng.random((64, 72, 3)).astype(np.float32)
    y = np.clip(x + 0.2 * rng.standard_normal(x.shape), 0, 1).astype(np.float32)
    bsd, lsd = torch.load(b, weights_only=True), torch.load(lin, weights_only=True)
    got = float(net(torch.from_numpy(x), torch.from_numpy(y)))
    assert got == pytest.approx(ref_lpips(x, y, bsd, lsd), rel=1e-4)
    assert got > 0
    assert float(net(torch.from_numpy(x), torch.from_numpy(x))) == 0.0
    batch = net(torch.from_numpy(np.stack([x, y])), torch.from_numpy(np.stack([y, y])))
    assert batch.shape == (2,) and float(batch[0]) == pytest.approx(got, rel=1e-5) and float(batch[1]) == 0.0


def test_evaluate_reports_lpips_when_weights_exist(tmp_path: Path) -> None:
    from test_eval import FakeModel, FakeScene, make_cameras, make_gaussians

    from atgs.eval.evaluate import EvalConfig, evaluate

    b, lin = write_standin_weights(tmp_path)
    cams, truth = make_cameras(w=40, h=32), make_gaussians(0)
    cfg = EvalConfig(backend="torch", progress=False, frames=(0,), lpips_backbone=b, lpips_linear=lin)
    res = evaluate(FakeModel(truth, cams), FakeScene(truth, cams, [1]), cfg)
    assert res.rows[0]["lpips"] == 0.0 and res.summary["lpips"] == {"available": True, "reason": ""}
    wrong = FakeModel(replace(truth, colors=1 - truth.colors), cams)
    assert evaluate(wrong, FakeScene(truth, cams, [1]), cfg).rows[0]["lpips"] > 0.0
    # images too small for AlexNet: reported unavailable with the reason, not a crash
    small = make_cameras()
    res = evaluate(FakeModel(truth, small), FakeScene(truth, small, [1]), cfg)
    assert res.rows[0]["lpips"] == "unavailable" and "smaller than 31 px" in res.summary["lpips"]["reason"]
