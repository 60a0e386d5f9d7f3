"""Several workers partitioned by both (--train.partition both, atgs.train.partition.both): four gloo
workers in two time groups of two. Each group holds one block of time segments, as a worker of the
time partition does, and its two workers share each of its steps' views, as the views partition
shares a step. So the run must equal the time partition on two workers (each a whole time group),
within float tolerance, and resume from and into it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from test_distributed import _assert_same_run, _free_port, _spawn
from test_distributed_time import HALF, _configs, _join, _scene


def _trainer(out: Path, workers, partition: str):
    """The time test's run (two segments, shared and own anchors, growth), two views per step and
    Gaussian dropout: each of a time group's workers renders one of its group's two views."""
    from atgs.train.trainer import Trainer

    m, t = _configs(partition)
    t.time_groups, t.drop_gaussians = 2, 0.4
    return Trainer(_scene(), m, t, out, progress=False, workers=workers)


def _in_halves(tr, d: Path, name: str) -> None:
    """Run ``tr`` to its end, saving ``name``_half.pt at HALF and ``name``.pt at the end."""
    tr.run_steps(progress=False, stop_at=HALF)
    tr.save(d / f"{name}_half.pt")
    tr.run_steps(progress=False)
    tr.save(d / f"{name}.pt")


def _resumed(d: Path, ckpt: str, name: str, workers, partition: str | None = None) -> None:
    """``ckpt`` resumed on ``workers`` (by ``partition``) to the end, saved as ``name``.pt."""
    from atgs.train.trainer import Trainer

    tr = Trainer.resume(_scene(), d / ckpt, d / name, workers=workers, partition=partition)
    tr.run_steps(progress=False)
    tr.save(d / f"{name}.pt")


def _time_worker(rank: int, world: int, port: int, d: Path) -> None:
    """The reference: partitioned by time on two workers, in two halves, and resumed at its half
    (a resume re-seeds the generators of time groups other than the first, so the resumed run is
    the reference of resumes); then the run partitioned by both, resumed at its half here (both
    -> time)."""
    workers = _join(rank, world, port)
    try:
        _in_halves(_trainer(d / "time", workers, "time"), d, "time")
        _resumed(d, "time_half.pt", "time_resumed", workers)
        if (d / "both_half.pt").exists():
            _resumed(d, "both_half.pt", "both_then_time", workers, partition="time")
    finally:
        workers.close()


def _both_worker(rank: int, world: int, port: int, d: Path) -> None:
    """Partitioned by both on four workers, in two halves, with its spread evaluations; then the
    time partition's half resumed by both (time -> both)."""
    workers = _join(rank, world, port)
    try:
        tr = _trainer(d / "both", workers, "both")
        _in_halves(tr, d, "both")
        p = tr.partition
        seen = {"time_rank": p.time_rank, "crew": [p.crew.rank, p.crew.world], "grids": tr.model.hash.num_grids,
                "segments": [p.part.segments.start, p.part.segments.stop], "own": tr.own_eval_frames(),
                "all": tr.eval_frames(), "periodic": tr.periodic_evaluation(),
                "final": tr.final_evaluation(None)}
        (d / f"both{rank}.json").write_text(json.dumps(seen))
        _resumed(d, "time_half.pt", "time_then_both", workers, partition="both")
    finally:
        workers.close()


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> tuple[Path, list[dict]]:
    d = tmp_path_factory.mktemp("both")
    _spawn(_time_worker, (2, _free_port(), d))
    _spawn(_both_worker, (4, _free_port(), d), n=4, timeout=240.0)
    again = d / "again"  # the reference once more, and the run by both resumed by time
    again.mkdir()
    (again / "both_half.pt").write_bytes((d / "both_half.pt").read_bytes())
    _spawn(_time_worker, (2, _free_port(), again))
    return d, [json.loads((d / f"both{r}.json").read_text()) for r in range(4)]


def test_both_partitions_at_once_train_as_the_time_partition_and_resume_from_and_into_it(runs) -> None:
    d, _ = runs
    _assert_same_run(d / "time.pt", d / "both.pt")
    _assert_same_run(d / "time_half.pt", d / "both_half.pt")
    _assert_same_run(d / "time.pt", d / "again" / "time.pt")  # (the reference repeats itself)
    _assert_same_run(d / "time_resumed.pt", d / "time_then_both.pt")  # time -> both
    _assert_same_run(d / "time_resumed.pt", d / "again" / "both_then_time.pt")  # both -> time


def test_each_time_group_holds_its_segments_and_its_workers_split_the_evaluation(runs) -> None:
    """Workers 0, 1 hold segment 0 and workers 2, 3 segment 1 (one grid each); every evaluation
    frame is scored once (a time group's workers split its frames); the spread evaluations are
    one process's evaluation of the gathered checkpoint."""
    from atgs.train.trainer import Trainer

    d, seen = runs
    assert [s["time_rank"] for s in seen] == [0, 0, 1, 1] and all(s["crew"] == [r % 2, 2] for r, s in enumerate(seen))
    assert [s["segments"] for s in seen] == [[0, 1], [0, 1], [1, 2], [1, 2]] and {s["grids"] for s in seen} == {1}
    assert sorted(f for s in seen for f in s["own"]) == seen[0]["all"] and all(s["own"] for s in seen)
    one = Trainer.resume(_scene(), d / "both.pt", d / "one")
    periodic = one.evaluate(frames=seen[0]["all"])
    assert seen[0]["periodic"] == seen[3]["periodic"]
    assert seen[0]["periodic"]["psnr"] == pytest.approx(periodic["psnr"], abs=1e-4)
    final = one.final_evaluation(None)
    assert seen[0]["final"]["views"] == final["views"]
    assert seen[0]["final"]["psnr"] == pytest.approx(final["psnr"], abs=1e-4)
    assert all(s["final"] is None for s in seen[1:])


def _unreduced_worker(rank: int, world: int, port: int, d: Path) -> None:
    """The run by both with a wrong exchange: each worker keeps its own share of the owned
    gradients (the time group's workers never sum them)."""
    from atgs.train.partition import both

    both.reduce_owned = lambda crew, owned, tables, reach: owned
    workers = _join(rank, world, port)
    try:
        tr = _trainer(d / "unreduced", workers, "both")
        tr.run_steps(progress=False, stop_at=HALF)
        tr.save(d / "unreduced.pt")
    finally:
        workers.close()


def test_a_time_group_that_does_not_sum_its_owned_gradients_fails_the_check(runs, tmp_path: Path) -> None:
    d, _ = runs
    _spawn(_unreduced_worker, (4, _free_port(), tmp_path), n=4, timeout=240.0)
    with pytest.raises(AssertionError, match="not close"):
        _assert_same_run(d / "time_half.pt", tmp_path / "unreduced.pt")



def test_time_groups_follow_the_partition_the_flag_and_the_nodes() -> None:
    """views: one group (every worker holds all); time: one per worker; both: the flag, or one per
    node without it, dividing the workers into groups of two or more blocks; the views of a step
    must cover the workers that share them."""
    from atgs.config_checks import ConfigError
    from atgs.train.distributed import check_settings, time_groups_of

    assert time_groups_of("views", 8) == 1 and time_groups_of("time", 8) == 8 and time_groups_of("time", 1) == 1
    assert time_groups_of("both", 8, 4) == 4 and time_groups_of("both", 8, 0, nodes=2) == 2
    assert time_groups_of("both", 8, 8) == 8  # (groups of one: the time partition)
    for asked, nodes in ((0, 1), (3, 1), (1, 1), (0, 3)):
        with pytest.raises(ConfigError, match="--train.time-groups G with G >= 2 dividing 8"):
            time_groups_of("both", 8, asked, nodes)
    check_settings(2, 8, "both", 4)  # two workers per group, two views
    with pytest.raises(ConfigError, match="the 4 workers of each time group share each step's views, but "
                                          "--train.views-per-step is 2; pass --train.views-per-step 4"):
        check_settings(2, 8, "both", 2)
    with pytest.raises(ConfigError, match="^8 workers share"):
        check_settings(2, 8, "views")
    check_settings(1, 8, "time")

# --- the command line: two "nodes" of torchrun on this machine ------------------------------------------

def _node(port: int, *args: str):
    """One node of ``torchrun --nnodes 2 --nproc-per-node 2`` (c10d rendezvous on this machine)."""
    import subprocess
    import sys

    from test_cli_promises import REPO, _env

    launcher = [sys.executable, "-m", "torch.distributed.run", "--nnodes", "2", "--nproc-per-node", "2",
                "--rdzv-backend", "c10d", "--rdzv-endpoint", f"127.0.0.1:{port}", "--rdzv-id", "both"]
    return subprocess.Popen([*launcher, "-m", "atgs.cli.train", *args, "--no-progress"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env={**_env(), "OMP_NUM_THREADS": "1"}, cwd=REPO)


def test_torchrun_on_two_nodes_gives_each_node_a_time_group_and_the_checkpoint_resumes(toy_scene_dir, tmp_path):
    """--nnodes 2 with --train.partition both and no --train.time-groups: one time group per node
    (the views exchange stays within a node), its checkpoint resumed by one process; on one
    machine, --workers 4 needs --train.time-groups (one line, exit code 2)."""
    from test_cli_promises import _finish, _last_line
    from test_distributed import _start

    out = tmp_path / "run"
    args = ("--data", str(toy_scene_dir), "--out", str(out), "tiny", "--train.iterations", "4",
            "--train.partition", "both", "--train.views-per-step", "2", "--train.eval-every", "2")
    port = _free_port()
    nodes = [_node(port, *args) for _ in range(2)]
    said = [p.communicate(timeout=240) for p in nodes]
    assert [p.returncode for p in nodes] == [0, 0], [e.decode(errors="replace")[-2000:] for _, e in said]
    stdout = b"".join(o for o, _ in said).decode()
    assert "x 4 workers (gloo, partitioned by both: 2 time groups of 2)" in stdout, stdout
    result = json.loads((out / "result.json").read_text())
    assert result["workers"]["time_group"]["workers"] == 2 and result["eval"]["views"] == 6, result
    data = torch.load(out / "ckpt.pt", weights_only=True)
    assert data["step"] == 4 and data["model"]["tmlp_w1"].shape[0] == 2, "both time groups' segments, once"
    code, err = _finish(_start("--out", str(out), "--data", str(toy_scene_dir), "--resume", "--train.iterations", "6"))
    assert code == 0 and "Traceback" not in err, err
    assert torch.load(out / "ckpt.pt", weights_only=True)["step"] == 6
    code, err = _finish(_start("--out", str(out), "--data", str(toy_scene_dir), "--resume", "--train.iterations", "8",
                               "--workers", "4"))
    assert code == 2 and "--train.time-groups" in _last_line(err) and "Traceback" not in err, err
