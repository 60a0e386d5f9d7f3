"""atgs-train argument handling (presets set the defaults of every flag)."""

import pytest

from atgs.cli.train import parse, run


def test_preset_defaults_and_overrides():
    a = parse(["--preset", "cpu-fast", "--iterations", "300", "--model.window", "3", "--train.lambda-ssim", "0.3"])
    assert a.preset == "cpu-fast" and a.iterations == 300
    assert a.model.feature_dim == 32 and a.model.window == 3
    assert a.train.iterations == 300 and a.train.lambda_ssim == 0.3
    assert a.train.lr.warmup_steps == 10, "the preset schedule is rescaled to --iterations"
    b = parse(["--preset=paper"])
    assert b.model.spatial_resolution == 128 and b.model.hash.log2_table_size == 16


def test_existing_checkpoint_is_not_overwritten(tmp_path):
    (tmp_path / "ckpt.pt").write_bytes(b"old")
    with pytest.raises(SystemExit, match="--resume"):
        run(parse(["--out", str(tmp_path), "--data", str(tmp_path)]))
    assert (tmp_path / "ckpt.pt").read_bytes() == b"old"
    with pytest.raises(SystemExit, match="not found"):
        run(parse(["--out", str(tmp_path / "new"), "--resume"]))
