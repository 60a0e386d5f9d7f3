"""atgs-eval end to end with real objects: a prepared scene on disk (atgs.data.scene), a real
(untrained, tiny) ATGS model saved by the trainer as ckpt.pt, the command-line entry point."""

from __future__ import annotations

import csv
import json
import math
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from atgs.cli.evaluate import main
from atgs.data.scene import MemoryScene, PreparedScene, write_prepared_scene
from atgs.eval import metrics as M
from test_eval import make_cameras, make_gaussians, moving, render

NUM_FRAMES = 4


def write_scene(root: Path, cams, test: tuple[str, ...] = ("cam02",)) -> Path:
    truth = make_gaussians(0, n=30)

    def frame(ci: int, f: int) -> np.ndarray:
        return render(moving(truth, f), cams[ci]).numpy()

    pts = torch.cat([moving(truth, 0).means, moving(truth, 3).means]).numpy()
    cols = torch.cat([truth.colors, truth.colors]).numpy()
    kfs = np.repeat([0, 1], len(truth))
    return write_prepared_scene(root, MemoryScene(cams, NUM_FRAMES, 10.0, [0, 3], pts, kfs, list(test),
                                                  point_colors=cols), frame)


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    from atgs.train.config import preset
    from atgs.train.trainer import Trainer

    root = tmp_path_factory.mktemp("e2e")
    data = write_scene(root / "scene", make_cameras(3, w=40, h=32))
    model_cfg, train_cfg = preset("tiny")
    train_cfg = replace(train_cfg, render_backend="torch", background=(0.0, 0.0, 0.0))
    ckpt = Trainer(PreparedScene.load(data), model_cfg, train_cfg, root / "run").save()
    return ckpt, data


def test_cli_scores_real_checkpoint(trained: tuple[Path, Path], tmp_path: Path,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    import atgs

    ckpt, data = trained
    out = tmp_path / "eval"
    rc = main([str(ckpt), "--data", str(data), "--out", str(out), "--backend", "torch", "--no-progress",
               "--every", "2", "--images-per-camera", "1"])
    assert rc == 0, capsys.readouterr().err
    assert "lpips unavailable" in capsys.readouterr().out
    rows = list(csv.DictReader(open(out / "per_view.csv")))
    assert [(r["camera"], r["frame"]) for r in rows] == [("cam02", "0"), ("cam02", "2")]
    model, scene = atgs.load(ckpt), PreparedScene.load(data)
    for r in rows:
        f = int(r["frame"])
        img = render(model.gaussians_at_frame(f), scene.cameras[2]).double()
        gt = torch.from_numpy(scene.image(2, f)).double()
        assert float(r["psnr"]) == pytest.approx(float(M.psnr(img, gt)), abs=1e-4)
        assert float(r["ssim"]) == pytest.approx(float(M.ssim(img, gt)), abs=1e-5)
        assert math.isfinite(float(r["psnr"]))
    summary = json.loads((out / "summary.json").read_text())
    assert summary["settings"]["data"] == str(data.resolve()) and summary["settings"]["background"] == [0, 0, 0]
    assert summary["lpips"]["available"] is False
    assert (out / "images" / "cam02" / "000000.png").is_file()


def with_data_dir(ckpt: Path, tmp: Path, data_dir: Path) -> Path:
    from atgs.checkpoint import read_checkpoint, save_checkpoint

    d = read_checkpoint(ckpt)
    d["data_dir"] = str(data_dir)
    save_checkpoint(tmp / "with_data.pt", {k: v for k, v in d.items() if k not in ("format", "version")})
    return tmp / "with_data.pt"


def without_data_dir(ckpt: Path, tmp: Path) -> Path:
    from atgs.checkpoint import read_checkpoint, save_checkpoint

    d = read_checkpoint(ckpt)
    for k in ("data_dir", "data"):
        d.pop(k, None)
        d.get("train_config", {}).pop(k, None)
    save_checkpoint(tmp / "without_data.pt", {k: v for k, v in d.items() if k not in ("format", "version")})
    return tmp / "without_data.pt"


def test_cli_uses_data_dir_recorded_in_checkpoint(trained: tuple[Path, Path], tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    ckpt, data = trained
    rc = main([str(with_data_dir(ckpt, tmp_path, data)), "--backend", "torch", "--no-progress", "--frames", "1",
               "--images-per-camera", "0"])
    assert rc == 0, capsys.readouterr().err
    summary = json.loads((tmp_path / "eval" / "summary.json").read_text())  # default: eval/ beside the ckpt
    assert summary["settings"]["data"] == str(data.resolve()) and summary["num_views"] == 1


def test_cli_errors_are_one_line_exit_2(trained: tuple[Path, Path], tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    ckpt, data = trained
    cams = make_cameras(3, w=40, h=32)
    shifted = [replace(c, w2c=c.w2c.copy()) for c in cams]
    shifted[2].w2c[0, 3] += 0.5  # one test camera moved: the scene is not the one trained on
    other = write_scene(tmp_path / "other", shifted)
    holes = tmp_path / "holes"
    shutil.copytree(data, holes)
    (holes / "images" / "cam02" / "000001.png").unlink()
    cases = [
        ([str(tmp_path / "nope.pt")], "checkpoint not found"),
        ([str(data / "scene.json")], "not a readable ATGS checkpoint"),
        ([str(without_data_dir(ckpt, tmp_path))], "does not record its data directory; pass --data"),
        ([str(ckpt), "--data", str(tmp_path / "missing")], "not a directory"),
        ([str(ckpt), "--data", str(other)], "camera 'cam02' differs between the checkpoint and the scene"),
        ([str(ckpt), "--data", str(data), "--frames", "9"], r"--frames: [9] out of range [0, 4)"),
        ([str(ckpt), "--data", str(holes)], "cam02/000001.png: frame file missing"),
    ]
    for argv, message in cases:
        out = tmp_path / "out"
        rc = main([*argv, "--out", str(out), "--backend", "torch", "--no-progress"])
        err = capsys.readouterr().err.strip()
        assert rc == 2 and message in err and "\n" not in err and err.startswith("atgs-eval: error: "), (argv, err)
        assert not out.exists()
