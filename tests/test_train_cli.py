"""atgs-train argument handling (presets set the defaults of every flag); the promises about the
run directory and Ctrl-C are in tests/test_cli_promises.py."""

from atgs.cli.train import parse


def test_preset_defaults_and_overrides():
    a = parse(["--preset", "cpu-fast", "--iterations", "300", "--model.window", "3", "--train.lambda-ssim", "0.3"])
    assert a.preset == "cpu-fast" and a.iterations == 300
    assert a.model.feature_dim == 32 and a.model.window == 3
    assert a.train.iterations == 300 and a.train.lambda_ssim == 0.3
    assert a.train.lr.warmup_steps == 10, "the preset schedule is rescaled to --iterations"
    b = parse(["--preset=paper"])
    assert b.model.spatial_resolution == 128 and b.model.hash.log2_table_size == 16


def test_raw_train_iterations_is_a_step_count_not_resized_by_the_budget():
    """--train.iterations alone used to be re-sized by the preset's 20-minute budget (a user asking
    for 60 steps trained for 20 minutes, and the save interval scaled past the end of the run)."""
    a = parse(["--preset", "cpu", "--train.iterations", "60"])
    assert a.iterations == 60 and a.train.iterations == 60
    assert a.train.save_every <= 500 and a.train.lr.warmup_steps == 2, "the preset schedule is rescaled"
    b = parse(["--preset", "cpu", "--train.iterations", "60", "--minutes", "3"])
    assert b.iterations is None and b.minutes == 3, "a budget given with it still wins"


def test_auto_applies_scene_choices_and_keeps_explicit_flags(tmp_path, capsys):
    """--auto on a static scene picks K = M = 1; a --model.* flag given explicitly wins."""
    import numpy as np

    from atgs.cameras import Camera, look_at
    from atgs.cli.train import apply_auto, explicit_model_flags
    from atgs.data.scene import MemoryScene, PreparedScene, write_prepared_scene

    K = np.array([[40.0, 0, 24], [0, 40.0, 16], [0, 0, 1]])
    cams = [Camera(f"cam{i:02d}", 48, 32, K, look_at([3 * np.cos(i), 3 * np.sin(i), 1.0], [0, 0, 0]))
            for i in range(3)]
    still = np.random.default_rng(0).random((32, 48, 3)).astype(np.float32)
    pts = np.random.default_rng(1).random((50, 3)) - 0.5
    write_prepared_scene(tmp_path / "s", MemoryScene(cams, 12, keyframes=[0, 5, 11], points=pts,
                                                     point_keyframes=np.arange(50) % 3,
                                                     point_colors=np.full((50, 3), 0.5)), lambda c, f: still)
    scene = PreparedScene.load(tmp_path / "s")

    argv = ["--auto", "--preset", "cpu-fast", "--model.spatial-resolution", "17"]
    args = parse(argv)
    explicit = explicit_model_flags(argv)
    assert explicit == {"spatial_resolution"}
    apply_auto(args, scene, explicit)
    assert args.model.num_keyframes == 1 and args.model.num_segments == 1, "a static scene needs one of each"
    assert args.model.spatial_resolution == 17, "explicit flags win over --auto"
    assert "kept the given value" in capsys.readouterr().out
