"""A worker restarted by torchrun (--max-restarts) continues only the run its start began: the
run's identity travels in every checkpoint (atgs.train.run_dir). The launcher is simulated in
one process: torchrun's environment (TORCHELASTIC_RUN_ID, TORCHELASTIC_RESTART_COUNT) and a
worker failure raised inside the steps; tests/test_distributed.py kills a real worker."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch

from atgs.cli.train import main as train_main
from atgs.train.distributed import WorkerLost
from atgs.train.trainer import Trainer


def _ckpt(out: Path) -> dict:
    return torch.load(out / "ckpt.pt", weights_only=True)


def _logged(out: Path) -> list[int]:
    return [int(r.split(",")[0]) for r in (out / "train_log.csv").read_text().strip().splitlines()[1:]]


def _launch(monkeypatch, start: str | None, restart: int = 0) -> None:
    """The environment torchrun gives a worker of start ``start`` (None: no torchrun) at attempt ``restart``."""
    for name, value in (("TORCHELASTIC_RUN_ID", start), ("TORCHELASTIC_RESTART_COUNT", str(restart))):
        if start is None:
            monkeypatch.delenv(name, raising=False)
        else:
            monkeypatch.setenv(name, value)


def _fail_at(monkeypatch, step: int) -> None:
    """A worker failing when the run reaches ``step`` (before training step ``step + 1``)."""
    real = Trainer.train_step

    def train_step(self, *args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        if self.step >= step:
            raise WorkerLost("worker 0: lost the other workers (simulated)")
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Trainer, "train_step", train_step)


@pytest.fixture(scope="module")
def old_run(toy_scene_dir, tmp_path_factory) -> Path:
    """A finished 3-step run, started without torchrun (a random identity)."""
    out = tmp_path_factory.mktemp("old") / "run"
    with pytest.MonkeyPatch.context() as mp:
        _launch(mp, None)
        assert train_main(["--data", str(toy_scene_dir), "--out", str(out), "tiny", "--train.iterations", "3",
                           "--train.eval-every", "0", "--no-progress"]) == 0
    return out


def _over(old_run: Path, tmp_path: Path) -> Path:
    out = tmp_path / "run"
    shutil.copytree(old_run, out)
    return out


def _argv(scene: Path, out: Path, steps: int) -> list[str]:
    return ["--data", str(scene), "--out", str(out), "tiny", "--train.iterations", str(steps), "--overwrite",
            "--max-restarts", "1", "--train.save-every", "2", "--train.eval-every", "0", "--no-progress"]


def test_each_run_has_an_identity_in_its_checkpoints_and_config(old_run) -> None:
    run_id = _ckpt(old_run)["run_id"]
    assert isinstance(run_id, str) and len(run_id) >= 32
    assert json.loads((old_run / "config.json").read_text())["run_id"] == run_id


def test_a_restart_before_the_new_runs_first_checkpoint_starts_afresh_not_the_replaced_run(
        old_run, toy_scene_dir, tmp_path, monkeypatch, capsys) -> None:
    out, steps = _over(old_run, tmp_path), 5
    old_id = _ckpt(out)["run_id"]
    _launch(monkeypatch, "start-b")
    _fail_at(monkeypatch, 0)  # the first attempt fails before any checkpoint of the new run
    assert train_main(_argv(toy_scene_dir, out, steps)) == 2
    assert _ckpt(out)["run_id"] == old_id and "lost the other workers" in capsys.readouterr().err
    monkeypatch.undo()
    _launch(monkeypatch, "start-b", restart=1)
    assert train_main(_argv(toy_scene_dir, out, steps)) == 0
    said = capsys.readouterr().out
    assert (f"atgs-train: restarted by the launcher after a worker failed (restart 1); {out / 'ckpt.pt'} is "
            "another run's (this start wrote none yet): starting afresh, as the first start did") in said, said
    assert "resuming at step" not in said
    ckpt = _ckpt(out)
    assert ckpt["run_id"] == "start-b" and ckpt["step"] == steps
    assert json.loads((out / "result.json").read_text())["steps"] == steps, "trained from step 0, not the old run's 3"
    assert _logged(out) == list(range(1, steps + 1))


def test_a_restart_after_the_new_runs_first_checkpoint_continues_it_and_resume_keeps_its_identity(
        old_run, toy_scene_dir, tmp_path, monkeypatch, capsys) -> None:
    out, steps = _over(old_run, tmp_path), 5
    _launch(monkeypatch, "start-c")
    _fail_at(monkeypatch, 3)  # after the checkpoint of step 2 (--train.save-every 2)
    assert train_main(_argv(toy_scene_dir, out, steps)) == 2
    assert _ckpt(out)["run_id"] == "start-c" and _ckpt(out)["step"] == 2
    monkeypatch.undo()
    capsys.readouterr()
    _launch(monkeypatch, "start-c", restart=1)
    assert train_main(_argv(toy_scene_dir, out, steps)) == 0
    said = capsys.readouterr().out
    assert (f"atgs-train: restarted by the launcher after a worker failed (restart 1); continuing from "
            f"{out / 'ckpt.pt'}") in said and "resuming at step 2 of 5" in said, said
    assert _ckpt(out)["run_id"] == "start-c" and _ckpt(out)["step"] == steps
    assert _logged(out) == list(range(1, steps + 1))
    # a user's --resume, in another start: the run keeps its identity
    _launch(monkeypatch, "start-d")
    assert train_main(["--data", str(toy_scene_dir), "--out", str(out), "--resume", "--train.iterations", str(steps + 1),
                       "--no-progress"]) == 0
    assert _ckpt(out)["run_id"] == "start-c" and _ckpt(out)["step"] == steps + 1
    assert json.loads((out / "config.json").read_text())["run_id"] == "start-c"


def test_a_restart_without_a_start_identity_does_not_continue_a_checkpoint(old_run, tmp_path, monkeypatch,
                                                                            capsys) -> None:
    from atgs.cli.train import restarted_run
    from atgs.cli.train_args import parse

    out = _over(old_run, tmp_path)
    _launch(monkeypatch, "none", restart=1)  # several machines, no --rdzv-id: every start is "none"
    assert not restarted_run(parse(["--out", str(out), "--overwrite"]))
    assert "cannot be told from another run's without torchrun's --rdzv-id" in capsys.readouterr().out
    assert restarted_run(parse(["--out", str(out), "--resume"])), "a --resume start continues the run there"
    _launch(monkeypatch, "start-e", restart=0)
    assert not restarted_run(parse(["--out", str(out), "--overwrite"])), "the first start is no restart"
