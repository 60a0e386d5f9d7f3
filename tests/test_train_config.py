"""The configs check themselves (one-line errors naming the flag, before anything touches --out),
one rule sizes a schedule from a step count however the count was chosen, config.json says what
ran, and the trainer gives torch's thread count back."""

from __future__ import annotations

import dataclasses
import json
import typing

import pytest
import torch

from atgs.cli.train import main as train_main
from atgs.cli.train_args import Preset, parse
from atgs.config_checks import ConfigError
from atgs.model.config import ModelConfig
from atgs.train.config import PRESET_NAMES, PresetName, TrainConfig, preset
from atgs.train.step_schedule import SCHEDULE_SETTINGS, RULES, schedule_for, schedule_of
from atgs.train.trainer import Trainer
from builders import make_toy_scene


@pytest.mark.parametrize("flags, named", [
    (["--train.iterations", "-5"], "--train.iterations -5"),
    (["--train.minutes", "-1"], "--train.minutes -1"),
    (["--train.densify.interval", "0"], "--train.densify.interval 0"),
    (["--train.lambda-volume", "-0.1"], "--train.lambda-volume -0.1"),
    (["--model.num-segments", "0"], "--model.num-segments 0"),
])
def test_a_bad_value_is_one_line_before_anything_touches_out(flags, named, toy_scene_dir, tmp_path, capsys):
    """--train.iterations -5 used to train 0 steps, score the untrained model and write a checkpoint."""
    out = tmp_path / "run"
    code = train_main(["--data", str(toy_scene_dir), "--out", str(out), "tiny", "--no-progress", *flags])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith(f"atgs-train: error: {named}") and "\n" not in err, err
    assert not out.exists(), "nothing is written"


def test_configs_refuse_values_out_of_range_in_code_too():
    with pytest.raises(ConfigError, match="--train.volume-reduction 'median': use one of sum, mean, mean-voxel"):
        TrainConfig(volume_reduction="median")
    with pytest.raises(ConfigError, match="--train.camera-exposure 'maybe'"):
        TrainConfig(camera_exposure="maybe")
    with pytest.raises(ConfigError, match="--train.render-backend 'gpu'"):
        TrainConfig(render_backend="gpu")
    with pytest.raises(ConfigError, match="--model.hash.levels 0"):
        dataclasses.replace(ModelConfig().hash, levels=0)
    with pytest.raises(ConfigError, match="preset 'huge'"):
        preset("huge")
    with pytest.raises(ConfigError, match="--train.fixed-schedule"):
        TrainConfig(fixed_schedule=("warmup",))
    # a field set after construction: the trainer asks again before any work
    m, t = preset("tiny")
    t.views_per_step = 0
    with pytest.raises(ConfigError, match="--train.views-per-step 0: use >= 1"):
        Trainer(make_toy_scene(num_frames=4, num_cameras=4, width=32, height=24, keyframes=2), m, t, "unused")


def test_the_preset_names_have_one_owner():
    assert typing.get_type_hints(Preset)["name"] is PresetName
    assert typing.get_args(PresetName) == PRESET_NAMES
    for name in PRESET_NAMES:
        assert parse([name]).preset.name == name
    assert set(RULES) == set(SCHEDULE_SETTINGS)


def test_iterations_and_a_budget_that_lands_on_the_same_steps_train_the_same_schedule(tmp_path):
    """The cpu preset at 1,000 steps: --train.iterations 1000 densified every 50 steps and evaluated
    every 500, a --train.minutes budget that planned 1,000 steps every 17 and 250 (it scaled the
    preset's 5,000-step schedule). One rule sizes both now."""
    fixed = parse(["cpu", "--train.iterations", "1000"]).train
    scene = make_toy_scene(num_frames=6, num_cameras=4, width=32, height=24, keyframes=3)
    m, _ = preset("tiny")
    pace = 0.5
    # the first plan at step 6 (1 skipped, 5 timed): 994 steps more at 0.5 s each, and the final
    # evaluation's reserve: measured on the simulated clock, where evaluating takes no time, 1 s
    seconds = 6 * pace + 1.0 + 994 * pace + 0.25
    t = dataclasses.replace(preset("cpu")[1], minutes=seconds / 60, velocity_from_flow=False)
    tr = Trainer(scene, m, t, tmp_path)
    tr.budget.skip_steps, tr.budget.calibration_steps = 1, 5
    tr.clock = lambda: pace * tr.step
    tr.run_steps(progress=False, stop_at=7)
    assert tr.budget.pace == pytest.approx(pace) and tr.cfg.iterations == 1000
    assert schedule_of(tr.cfg) == schedule_of(fixed)
    saved = torch.load(tmp_path / "ckpt.pt", weights_only=True)["train_config"]
    assert (saved["iterations"], saved["densify"]["interval"], saved["eval_every"]) == (1000, 50, 500)


def test_a_step_count_and_a_budget_are_one_or_the_other():
    a = parse(["cpu", "--train.iterations", "60", "--train.minutes", "0"])
    assert a.iterations == 60 and a.train.minutes == 0 and a.train.lr.warmup_steps == 2, "no budget: a step count"
    b = parse(["cpu", "--train.minutes", "3"])
    assert b.iterations is None and b.minutes == 3 and b.train.minutes == 3
    with pytest.raises(ConfigError, match="--train.iterations and --train.minutes 3 were both given"):
        parse(["cpu", "--train.iterations", "60", "--train.minutes", "3"])


def test_schedule_flags_given_are_kept_at_any_step_count():
    a = parse(["cpu", "--train.iterations", "4000", "--train.eval-every", "100",
               "--train.densify.interval=30"])
    assert (a.train.eval_every, a.train.densify.interval) == (100, 30)
    assert a.train.densify.start == 4000 // 20, "the others follow the step count"
    b = parse(["cpu", "--train.eval-every", "100"])  # a budget re-sizes the rest
    sized = schedule_for(b.train, 1000)
    assert sized.eval_every == 100 and sized.densify.interval == max(50, 1000 // 60)
    paper = preset("paper", iterations=1000)[1]  # the paper's schedule at any step count
    assert {k: v for k, v in schedule_of(paper).items() if k != "iterations"} == \
        {k: v for k, v in schedule_of(preset("paper")[1]).items() if k != "iterations"}


def test_config_json_says_what_ran_and_follows_a_resume(toy_scene_dir, tmp_path):
    out = tmp_path / "run"
    assert train_main(["--data", str(toy_scene_dir), "--out", str(out), "tiny", "--train.iterations", "2",
                       "--train.camera-exposure", "auto", "--no-progress"]) == 0
    config = json.loads((out / "config.json").read_text())
    saved = json.loads(json.dumps(torch.load(out / "ckpt.pt", weights_only=True)["train_config"]))
    assert config["train"] == saved and config["train"]["camera_exposure"] in ("on", "off"), "resolved"
    assert train_main(["--data", str(toy_scene_dir), "--out", str(out), "--resume", "--train.iterations", "3",
                       "--no-progress"]) == 0
    config = json.loads((out / "config.json").read_text())
    assert config["preset"] == "tiny" and config["train"]["iterations"] == 3


def test_the_trainer_gives_torch_its_thread_count_back(tmp_path):
    scene = make_toy_scene(num_frames=4, num_cameras=4, width=32, height=24, keyframes=2)
    m, t = preset("tiny")
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        t.threads = 1
        tr = Trainer(scene, m, t, tmp_path)
        assert torch.get_num_threads() == 2, "after the set-up"
        seen = []
        real = tr.compute_loss
        tr.compute_loss = lambda *a: (seen.append(torch.get_num_threads()), real(*a))[1]
        tr.train_step()
        assert seen and set(seen) == {1} and torch.get_num_threads() == 2, "the run's inside, torch's after"
    finally:
        torch.set_num_threads(before)
