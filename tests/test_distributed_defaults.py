"""Defaults that work on several workers (issue 51): a new run launched on N workers without
--train.views-per-step takes the fewest views per step its workers can share (one each) and says
so in the start-up line; a value given that cannot work keeps its one-line error."""

from __future__ import annotations

import subprocess
import sys

import pytest

from test_cli_promises import REPO, _env, _finish, _last_line


def _smallest_that_passes(views: int, workers: int, partition: str, groups: int) -> int:
    """The reference: the first count from ``views`` on that the settings check accepts."""
    from atgs.config_checks import ConfigError
    from atgs.train.distributed import check_settings

    for v in range(views, 10 * workers):
        try:
            check_settings(v, workers, partition, groups)
            return v
        except ConfigError:
            continue
    raise AssertionError("no count works")


@pytest.mark.parametrize("views,workers,partition,groups", [
    (1, 2, "views", 0), (1, 8, "views", 0), (3, 2, "views", 0), (1, 8, "both", 2), (1, 8, "both", 4),
    (6, 8, "both", 2), (1, 4, "time", 0), (1, 1, "views", 0)])
def test_the_views_chosen_are_the_fewest_the_workers_can_share(views, workers, partition, groups) -> None:
    from atgs.train.distributed import views_that_work

    assert views_that_work(views, workers, partition, groups) == _smallest_that_passes(views, workers, partition, groups)


def test_torchrun_without_views_per_step_trains_and_says_what_it_chose(toy_scene_dir, tmp_path) -> None:
    """The command of issue 51, `torchrun --standalone --nproc-per-node 2 -m atgs.cli.train
    --data D --out O` (the tiny preset's one view per step), trains; its start-up line names the
    two views per step it chose, and the checkpoint holds them."""
    import torch

    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
                           "-m", "atgs.cli.train", "--data", str(toy_scene_dir), "--out", str(out), "--preset", "tiny",
                           "--iterations", "2", "--train.eval-every", "0", "--no-progress"],
                          capture_output=True, env={**_env(), "OMP_NUM_THREADS": "1"}, cwd=REPO, timeout=240)
    stdout, stderr = proc.stdout.decode(), proc.stderr.decode(errors="replace")
    assert proc.returncode == 0, stderr[-2000:]
    assert ("x 2 workers (gloo, partitioned by views), 2 views per step (--train.views-per-step not given; "
            "1 is too few for them)") in stdout, stdout
    data = torch.load(out / "ckpt.pt", weights_only=True)
    assert data["step"] == 2 and data["train_config"]["views_per_step"] == 2


def test_a_views_per_step_given_that_the_workers_cannot_share_is_refused_in_one_line(toy_scene_dir, tmp_path):
    proc = subprocess.Popen([sys.executable, "-m", "atgs.cli.train", "--data", str(toy_scene_dir), "--out",
                             str(tmp_path / "run"), "--preset", "tiny", "--workers", "2",
                             "--train.views-per-step", "1", "--no-progress"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=_env(), cwd=REPO)
    code, err = _finish(proc)
    assert code == 2 and "Traceback" not in err, err
    assert _last_line(err).endswith("2 workers share each step's views, but --train.views-per-step is 1; "
                                    "pass --train.views-per-step 2 (or a multiple of it)"), err
    assert not (tmp_path / "run").exists()
