"""Training on several workers (atgs.train.distributed): two gloo workers on the CPU update the model
as one process does with the same global batch and seed; checkpoints move between one and two
workers; Ctrl-C and a killed worker leave a checkpoint that resumes."""

from __future__ import annotations

import os
from pathlib import Path
import re
import signal
import socket
import subprocess
import sys
import time

import pytest
import torch
import torch.multiprocessing as mp

from builders import growing_tiny_config, make_toy_scene
from test_cli_promises import REPO, _env, _finish, _last_line

STEPS, HALF = 12, 6  # steps of the runs compared; the checkpoint that changes the number of workers


def _scene():
    return make_toy_scene(num_frames=6, num_cameras=4, width=40, height=32, keyframes=3)


def _configs():
    """The tiny preset, growing from step 4 on; four views of two cameras per step (two for each
    worker: their gradients merge locally first), random backgrounds (drawn ahead for the whole
    step), learned camera exposure (a second dense gradient), Gaussian dropout (each render's
    draw its own, whichever worker renders it)."""
    m, t = growing_tiny_config(STEPS)
    t.views_per_step, t.cameras_per_frame, t.random_background, t.camera_exposure = 4, 2, True, "on"
    t.drop_gaussians = 0.4
    return m, t


def _trainer(out: Path, workers=None):
    from atgs.train.trainer import Trainer

    m, t = _configs()
    return Trainer(_scene(), m, t, out, progress=False, workers=workers)


def _worker(rank: int, world: int, port: int, d: Path) -> None:
    """One of two workers (torch.multiprocessing): the run in two halves (its checkpoint at HALF for
    the 2 -> 1 resume), the one-process checkpoint at HALF resumed (1 -> 2), and the same run with
    a wrong reduction: each worker's loss divided by its own views instead of the step's."""
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE=str(world),
                      LOCAL_RANK=str(rank), LOCAL_WORLD_SIZE=str(world))
    from atgs.train.distributed import Workers
    from atgs.train.trainer import Trainer

    workers = Workers.from_env(torch.device("cpu"), timeout_s=60)
    try:
        tr = _trainer(d / "two", workers)
        tr.run_steps(progress=False, stop_at=HALF)
        tr.save(d / "two_half.pt")
        tr.run_steps(progress=False)
        tr.save(d / "two.pt")
        torch.save({"model": tr.model.state_dict(), "sparse_opt": tr.sparse_opt.state_dict(),
                    "dense_opt": tr.dense_opt.state_dict(), "generator": tr.gen.get_state()}, d / f"replica{rank}.pt")
        tr = Trainer.resume(_scene(), d / "one_half.pt", d / "one_then_two", workers=workers)
        tr.run_steps(progress=False)
        tr.save(d / "one_then_two.pt")
        right = Trainer.compute_loss
        Trainer.compute_loss = lambda self, *a: right(self, *a) * world  # each divided by its 2 views of 4
        tr = _trainer(d / "undivided", workers)
        tr.run_steps(progress=False)
        tr.save(d / "undivided.pt")
    finally:
        workers.close()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _spawn(fn, args: tuple, n: int = 2, timeout: float = 120.0) -> None:
    """``fn(rank, *args)`` in ``n`` processes; fails on an error or after ``timeout`` seconds."""
    ctx = mp.start_processes(fn, args=args, nprocs=n, join=False, start_method="spawn")
    deadline = time.monotonic() + timeout
    while not ctx.join(timeout=1.0):
        if time.monotonic() > deadline:
            for p in ctx.processes:
                p.kill()
            raise AssertionError(f"the workers did not finish within {timeout} s")


def _tensors(tree, prefix: str = "") -> dict:
    """Every tensor and plain value of a checkpoint's nested dicts and lists, by path."""
    if isinstance(tree, dict):
        return {k: v for key, sub in tree.items() for k, v in _tensors(sub, f"{prefix}/{key}").items()}
    if isinstance(tree, (list, tuple)):
        return {k: v for i, sub in enumerate(tree) for k, v in _tensors(sub, f"{prefix}/{i}").items()}
    return {prefix: tree}


def _assert_same_run(a: Path, b: Path) -> None:
    """The model and every trainer state (optimizers, statistics, sampler, generator) of two
    checkpoints agree, within float tolerance (the workers sum gradients in another order)."""
    ta, tb = (_tensors({k: torch.load(p, weights_only=True)[k] for k in ("step", "model", "trainer")})
              for p in (a, b))
    assert ta.keys() == tb.keys()
    for k in ta:
        if isinstance(ta[k], torch.Tensor):
            torch.testing.assert_close(tb[k], ta[k], rtol=1e-4, atol=1e-5, msg=lambda m, k=k: f"{k}: {m}")
        elif not k.startswith("/trainer/budget"):
            assert tb[k] == ta[k], k


def test_two_workers_update_the_model_as_one_process_and_resume_either_way(tmp_path: Path) -> None:
    from atgs.train.trainer import Trainer

    one = _trainer(tmp_path / "one")
    one.run_steps(progress=False, stop_at=HALF)
    one.save(tmp_path / "one_half.pt")
    one.run_steps(progress=False)
    one.save(tmp_path / "one.pt")
    _spawn(_worker, (2, _free_port(), tmp_path))
    two_then_one = Trainer.resume(_scene(), tmp_path / "two_half.pt", tmp_path / "two_then_one")
    two_then_one.run_steps(progress=False)
    two_then_one.save(tmp_path / "two_then_one.pt")

    assert one.step == STEPS and one.model.num_anchors > 100, "anchors grew (densification on the workers too)"
    _assert_same_run(tmp_path / "one.pt", tmp_path / "two.pt")
    _assert_same_run(tmp_path / "one.pt", tmp_path / "one_then_two.pt")  # resumed 1 -> 2
    _assert_same_run(tmp_path / "one.pt", tmp_path / "two_then_one.pt")  # resumed 2 -> 1
    r0, r1 = (_tensors(torch.load(tmp_path / f"replica{r}.pt", weights_only=True)) for r in (0, 1))
    assert all(torch.equal(r0[k], r1[k]) if isinstance(r0[k], torch.Tensor) else r0[k] == r1[k] for k in r0), \
        "every worker holds the same model and optimizer"
    with pytest.raises(AssertionError, match="exp_avg"):  # the check sees a wrong normalisation
        _assert_same_run(tmp_path / "one.pt", tmp_path / "undivided.pt")


# --- the command line: atgs-train --workers 2 (torchrun's launcher) ----------------------------------

def _start(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "atgs.cli.train", *args, "--no-progress"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=_env(), cwd=REPO)


def _two_workers_until_checkpoint(scene: Path, out: Path) -> subprocess.Popen:
    """atgs-train --workers 2 on the toy scene, endless, once it wrote its first checkpoint."""
    proc = _start("--data", str(scene), "--out", str(out), "tiny", "--train.iterations", "100000",
                  "--train.views-per-step", "2", "--train.save-every", "3", "--train.eval-every", "0", "--workers", "2")
    deadline = time.monotonic() + 120
    while not (out / "ckpt.pt").is_file():
        assert proc.poll() is None, proc.communicate()[1].decode(errors="replace")
        assert time.monotonic() < deadline, "no checkpoint within 120 s"
        time.sleep(0.2)
    return proc


def _worker_pid(launcher: int, rank: int) -> int:
    """The pid of worker ``rank`` among the launcher's children (torchrun sets RANK in their environment)."""
    for task in Path(f"/proc/{launcher}/task").iterdir():
        for pid in (task / "children").read_text().split():
            env = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
            if f"RANK={rank}".encode() in env:
                return int(pid)
    raise AssertionError(f"no worker of rank {rank} under pid {launcher}")


def _step(ckpt: Path) -> int:
    return int(torch.load(ckpt, weights_only=True)["step"])


def test_ctrl_c_on_two_workers_saves_a_checkpoint_that_one_and_two_workers_continue(toy_scene_dir, tmp_path):
    from atgs.cli.train import main as train_main

    out = tmp_path / "run"
    proc = _two_workers_until_checkpoint(toy_scene_dir, out)
    proc.send_signal(signal.SIGINT)  # torchrun passes it on to the workers
    code, err = _finish(proc)
    step = _step(out / "ckpt.pt")
    assert code == 130 and "Traceback" not in err, err
    assert _last_line(err) == (f"atgs-train: interrupted: checkpoint of step {step} saved to {out / 'ckpt.pt'}; "
                               f"continue with atgs-train --out {out} --resume")
    assert train_main(["--out", str(out), "--data", str(toy_scene_dir), "--resume", "--train.iterations", str(step + 3),
                       "--no-progress"]) == 0  # 2 -> 1
    assert _step(out / "ckpt.pt") == step + 3
    proc = _start("--out", str(out), "--data", str(toy_scene_dir), "--resume", "--train.iterations", str(step + 6),
                  "--workers", "2")  # 1 -> 2
    code, err = _finish(proc)
    assert code == 0 and "Traceback" not in err, err
    assert _step(out / "ckpt.pt") == step + 6
    steps = [int(r.split(",")[0]) for r in (out / "train_log.csv").read_text().strip().splitlines()[1:]]
    assert steps == list(range(1, step + 7)), "one log, its rows following each other"


def test_a_killed_worker_stops_the_other_in_one_line_and_the_checkpoint_resumes(toy_scene_dir, tmp_path):
    from atgs.data.scene import PreparedScene
    from atgs.train.trainer import Trainer

    out = tmp_path / "run"
    proc = _two_workers_until_checkpoint(toy_scene_dir, out)
    victim = _worker_pid(proc.pid, 1)
    os.kill(victim, signal.SIGKILL)
    t0 = time.monotonic()
    code, err = _finish(proc)
    assert time.monotonic() - t0 < 30, "the other worker stopped instead of waiting for its timeout"
    assert code == 2 and "Traceback" not in err, err
    lines = [s for s in err.splitlines() if s.strip()]
    # (its next exchange fails, or torchrun's SIGTERM comes first)
    assert re.match(r"atgs-train: error: worker 0: (lost the other workers|stopped by the launcher) \(", lines[-2]), err
    assert lines[-1] == (f"atgs-train: error: worker 1 (pid {victim}) was killed by SIGKILL; the other workers "
                         f"stopped; {out / 'ckpt.pt'} holds the last checkpoint; continue with atgs-train --out {out} "
                         "--resume")
    resumed = Trainer.resume(PreparedScene.load(toy_scene_dir), out / "ckpt.pt", out)
    assert resumed.step == _step(out / "ckpt.pt") > 0


def test_torchrun_restarts_a_killed_worker_and_the_run_continues_from_its_checkpoint(toy_scene_dir, tmp_path):
    """--max-restarts 1: a worker killed after the first checkpoint; torchrun starts both again,
    they continue that checkpoint (as --resume) and the run ends normally at its step count."""
    out = tmp_path / "run"
    steps = 40
    proc = subprocess.Popen([sys.executable, "-m", "atgs.cli.train", "--data", str(toy_scene_dir), "--out", str(out),
                             "tiny", "--train.iterations", str(steps), "--train.views-per-step", "2",
                             "--train.save-every", "3", "--train.eval-every", "0", "--workers", "2",
                             "--max-restarts", "1", "--no-progress"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env(), cwd=REPO)
    deadline = time.monotonic() + 120
    while not (out / "ckpt.pt").is_file():
        assert proc.poll() is None, proc.communicate()[1].decode(errors="replace")
        assert time.monotonic() < deadline, "no checkpoint within 120 s"
        time.sleep(0.05)
    killed_at = _step(out / "ckpt.pt")
    assert killed_at < steps, "the run ended before the kill: make it longer"
    os.kill(_worker_pid(proc.pid, 1), signal.SIGKILL)
    stdout, stderr = proc.communicate(timeout=300)
    stdout, stderr = stdout.decode(errors="replace"), stderr.decode(errors="replace")
    assert proc.returncode == 0, stderr[-2000:]
    assert "restarted by the launcher after a worker failed (restart 1)" in stdout, stdout
    resumed_at = int(re.search(r"resuming at step (\d+) of", stdout).group(1))
    assert killed_at <= resumed_at < steps
    assert _step(out / "ckpt.pt") == steps
    logged = [int(r.split(",")[0]) for r in (out / "train_log.csv").read_text().strip().splitlines()[1:]]
    assert logged == list(range(1, steps + 1)), "one log, one row per step"


@pytest.mark.parametrize("partition", ["views", "time"])
def test_two_workers_with_a_time_budget_measure_the_final_evaluation_alike(toy_scene_dir, tmp_path, partition):
    """--train.minutes on two workers: as the budget's timing begins, each worker times the final
    evaluation on its own frames and all take rank 0's figure (a collective every worker reaches
    at the same step, whatever frames it holds); the run ends, evaluated, within its budget."""
    out = tmp_path / partition
    proc = _start("--data", str(toy_scene_dir), "--out", str(out), "tiny", "--train.minutes", "0.3",
                  "--train.views-per-step", "2", "--train.partition", partition, "--train.eval-every", "0",
                  "--workers", "2")
    _, err = proc.communicate(timeout=240)
    assert proc.returncode == 0, err.decode(errors="replace")
    budget = torch.load(out / "ckpt.pt", weights_only=True)["trainer"]["budget"]
    assert budget["view_cost"] is not None and budget["view_cost"] > 0, budget
    assert budget["used"] <= 0.3 * 60 + 2.0, budget
    assert (out / "eval" / "summary.json").is_file()
