"""atgs-train's command line: presets are tyro subcommands that fill every flag's default, the flags
given override them, each flag has one spelling and the old ones still work with a note; the
promises about the run directory and Ctrl-C are in tests/test_cli_promises.py."""

from dataclasses import replace
from pathlib import Path

import pytest

from atgs.cli.train_args import parse
from atgs.config_checks import ConfigError
from atgs.train.config import PRESET_HELP, PRESET_NAMES, preset


@pytest.mark.parametrize("name", PRESET_NAMES)
def test_a_preset_chosen_on_the_command_line_is_the_preset_table(name):
    """What the argv scan gave before (the table's configs as the defaults, nothing given over them)."""
    model, train = preset(name)
    a = parse([name])
    assert (a.preset.name, a.model, a.train, a.iterations, a.minutes) == (name, model, train, None, None)


def test_the_default_preset_is_cpu():
    model, train = preset("cpu")
    a = parse(["--data", "scene"])
    assert (a.preset.name, a.model, a.train) == ("cpu", model, train)


def test_flags_given_override_the_preset_and_the_run_flags_go_anywhere():
    a = parse(["--data", "D", "cpu-fast", "--model.window", "3", "--train.lambda-ssim", "0.3", "--out", "O"])
    model, train = preset("cpu-fast")
    assert a.model == replace(model, window=3) and a.train == replace(train, lambda_ssim=0.3)
    assert (a.data, a.out) == (Path("D"), Path("O"))
    b = parse(["cpu-fast", "--train.iterations", "300"])
    assert b.iterations == 300 and b.train == preset("cpu-fast", iterations=300)[1], \
        "the preset's schedule sized to the step count"
    assert b.train.lr.warmup_steps == 10
    c = parse(["paper", "--train.minutes=3"])
    assert c.minutes == 3 and c.train == preset("paper", minutes=3)[1]


def test_a_step_count_alone_is_not_resized_by_the_presets_budget():
    """--train.iterations alone used to be re-sized by the preset's 20-minute budget (a user asking
    for 60 steps trained for 20 minutes, and the save interval scaled past the end of the run)."""
    a = parse(["cpu", "--train.iterations", "60"])
    assert a.iterations == 60 and a.train.iterations == 60 and a.train.minutes == 0
    assert a.train.save_every <= 500 and a.train.lr.warmup_steps == 2, "the preset schedule is rescaled"


def test_old_spellings_work_for_one_release_with_a_one_line_note(capsys):
    old = parse(["--data", "D", "--model.window", "3", "--preset", "cpu-fast", "--iterations", "300"])
    notes = capsys.readouterr().err.splitlines()
    assert old == parse(["--data", "D", "cpu-fast", "--model.window", "3", "--train.iterations", "300"])
    assert notes == ["atgs-train: note: --preset cpu-fast is now a subcommand (atgs-train cpu-fast --data ...); "
                     "the old spelling goes in the next release",
                     "atgs-train: note: --iterations is now --train.iterations; the old spelling goes in the next "
                     "release"]
    assert parse(["--preset=paper", "--minutes=3"]) == parse(["paper", "--train.minutes=3"])
    assert "--minutes is now --train.minutes" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="--preset 'huge': use one of cpu-fast, cpu, cpu-accurate, paper, tiny"):
        parse(["--preset", "huge"])


def test_help_lists_the_presets_and_a_presets_help_its_values(capsys):
    with pytest.raises(SystemExit):
        parse(["--help"])
    out = capsys.readouterr().out
    assert all(name in out and PRESET_HELP[name] in out for name in PRESET_NAMES), out
    with pytest.raises(SystemExit):
        parse(["cpu-accurate", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "--train.minutes FLOAT" in out and "(default: 60.0)" in out and "(default: 20.0)" not in out


def test_auto_applies_scene_choices_and_keeps_explicit_flags(tmp_path, capsys):
    """--auto on a static scene picks K = M = 1; a --model.* flag given explicitly wins."""
    import numpy as np

    from atgs.cameras import Camera, look_at
    from atgs.cli.train import apply_auto
    from atgs.cli.train_args import explicit_model_flags
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

    argv = ["--auto", "cpu-fast", "--model.spatial-resolution", "17"]
    args = parse(argv)
    explicit = explicit_model_flags(argv)
    assert explicit == {"spatial_resolution"}
    apply_auto(args, scene, explicit)
    assert args.model.num_keyframes == 1 and args.model.num_segments == 1, "a static scene needs one of each"
    assert args.model.spatial_resolution == 17, "explicit flags win over --auto"
    assert "kept the given value" in capsys.readouterr().out
