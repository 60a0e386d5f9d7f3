"""The README's promises of every command line, checked on the real entry points:
bad input -> one line ``<command>: error: ...`` on stderr and exit code 2, never a traceback;
Ctrl-C during training -> a clean stop with a checkpoint that ``--resume`` continues;
an existing run directory is byte-identical after a refused or interrupted start."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from builders import write_tiny_checkpoint

REPO = Path(__file__).resolve().parent.parent


def _snapshot(root: Path) -> dict[str, bytes]:
    """Every file below ``root`` with its bytes (directories as b"<dir>")."""
    return {str(p.relative_to(root)): (b"<dir>" if p.is_dir() else p.read_bytes()) for p in sorted(root.rglob("*"))}


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    return env


def _default_sigint() -> None:
    # A shell starts background jobs with SIGINT ignored, and exec keeps that: the child Python
    # would then never see the Ctrl-C this test sends (pytest run with `&` hung here).
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _train(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "atgs.cli.train", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env=_env(), cwd=REPO, preexec_fn=_default_sigint)


def _read_until(stream, pattern: str, timeout: float = 120.0) -> str:
    """Bytes of ``stream`` until ``pattern`` (regex) matches what was read so far."""
    os.set_blocking(stream.fileno(), False)
    seen, deadline = b"", time.monotonic() + timeout
    while time.monotonic() < deadline:
        chunk = stream.read()
        if chunk:
            seen += chunk
            if re.search(pattern, seen.decode(errors="replace")):
                return seen.decode(errors="replace")
        time.sleep(0.02)
    raise AssertionError(f"{pattern!r} not seen within {timeout} s; got {seen[-500:]!r}")


def _finish(proc: subprocess.Popen, head: str = "") -> tuple[int, str]:
    os.set_blocking(proc.stderr.fileno(), True)
    _, err = proc.communicate(timeout=120)
    return proc.returncode, head + err.decode(errors="replace")


def _last_line(stderr: str) -> str:
    return [s for s in re.split(r"[\r\n]+", stderr) if s.strip()][-1]


# --- bad input: one line, exit code 2 -------------------------------------------------------------

def test_every_command_reports_bad_input_in_one_line_with_exit_code_2(tmp_path, capsys) -> None:
    from atgs.cli.evaluate import main as eval_main
    from atgs.cli.export import main as export_main
    from atgs.cli.prepare import main as prepare_main
    from atgs.cli.synth import main as synth_main
    from atgs.cli.train import main as train_main
    from atgs.viewer.cli import main as view_main, render_main

    missing = tmp_path / "missing"
    cases = [
        ("atgs-train", train_main, ["--data", str(missing), "--out", str(tmp_path / "run"), "--no-progress"],
         "scene.json: not found"),
        ("atgs-prepare", prepare_main, [str(missing), "--out", str(tmp_path / "p")], "source path does not exist"),
        ("atgs-synth", synth_main, [str(tmp_path / "s"), "--cameras", "1"], "cameras >= 2"),
        ("atgs-eval", eval_main, [str(missing / "ckpt.pt")], "checkpoint not found"),
        ("atgs-export", export_main, [str(missing / "ckpt.pt"), "--out", str(tmp_path / "plys")],
         "checkpoint not found"),
        ("atgs-view", view_main, [str(missing / "ckpt.pt"), "--headless"], "checkpoint not found"),
        ("atgs-render", render_main, [str(missing / "ckpt.pt"), "--out", str(tmp_path / "v.mp4")],
         "checkpoint not found"),
    ]
    for prog, main, argv, message in cases:
        assert main(argv) == 2, prog
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"{prog}: error: ") and message in err and "\n" not in err, (prog, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == [], "failed commands wrote nothing"


def test_a_diverging_run_stops_with_one_line(toy_scene_dir, tmp_path, capsys, monkeypatch) -> None:
    import atgs.train.trainer as trainer_mod
    from atgs.cli.train import main as train_main

    real = trainer_mod.rasterize_gaussians

    def nan_render(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        out = real(*args, **kwargs)
        out.image = out.image * float("nan")
        return out

    monkeypatch.setattr(trainer_mod, "rasterize_gaussians", nan_render)
    code = train_main(["--data", str(toy_scene_dir), "--out", str(tmp_path / "run"), "tiny",
                       "--train.max-bad-steps", "3", "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.count("\n") == 0 and "consecutive steps had a non-finite loss" in err, err
    assert not (tmp_path / "run").exists(), "nothing is written before the first checkpoint"


# --- Ctrl-C, resume, and the run directory -----------------------------------------------------------

@pytest.fixture(scope="module")
def interrupted_run(toy_scene_dir, tmp_path_factory) -> tuple[Path, int, str, int]:
    """atgs-train stopped with SIGINT in the middle of training: (run dir, exit code, stderr, step)."""
    out = tmp_path_factory.mktemp("interrupted") / "run"
    proc = _train("--data", str(toy_scene_dir), "--out", str(out), "tiny", "--train.iterations", "100000",
                  "--train.eval-every", "0", "--train.save-every", "0")
    head = _read_until(proc.stderr, r"\b([1-9]\d*)/100000\b")  # tqdm shows steps: the loop is running
    proc.send_signal(signal.SIGINT)
    code, err = _finish(proc, head)
    step = int(torch.load(out / "ckpt.pt", weights_only=True)["step"])
    return out, code, err, step


def test_ctrl_c_saves_a_checkpoint_that_resume_continues(interrupted_run) -> None:
    out, code, err, step = interrupted_run
    assert code == 130 and "Traceback" not in err, err
    assert _last_line(err) == (f"atgs-train: interrupted: checkpoint of step {step} saved to {out / 'ckpt.pt'}; "
                               f"continue with atgs-train --out {out} --resume")
    rows = (out / "train_log.csv").read_text().strip().splitlines()
    assert len(rows) == step + 1 and rows[-1].startswith(f"{step},"), "the log ends at the checkpoint"
    assert json.loads((out / "config.json").read_text())["preset"] == "tiny"
    assert not (out / "result.json").exists()

    from atgs.cli.train import main as train_main

    scene = json.loads((out / "config.json").read_text())["data"]
    assert train_main(["--out", str(out), "--data", scene, "--resume", "--train.iterations", str(step + 3),
                       "--no-progress"]) == 0
    assert int(torch.load(out / "ckpt.pt", weights_only=True)["step"]) == step + 3
    assert json.loads((out / "result.json").read_text())["steps"] == 3
    steps = [int(r.split(",")[0]) for r in (out / "train_log.csv").read_text().strip().splitlines()[1:]]
    assert steps == list(range(1, step + 4)), "resumed rows follow the interrupted ones"


def test_refused_and_interrupted_starts_leave_an_existing_run_byte_identical(interrupted_run, tmp_path,
                                                                            capsys) -> None:
    from atgs.cli.train import main as train_main

    out = interrupted_run[0]
    before = _snapshot(out)
    scene = json.loads((out / "config.json").read_text())["data"]
    # refused: the directory holds a run, and neither --resume nor --overwrite was given
    assert train_main(["--data", scene, "--out", str(out), "tiny", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("atgs-train: error: ") and "--overwrite" in err and "\n" not in err, err
    assert _snapshot(out) == before
    # interrupted before its first checkpoint: --overwrite, stopped while the built-in scene is built
    cache = tmp_path / "cache"
    proc = _train("--out", str(out), "--overwrite", "tiny", "--cache-dir", str(cache))
    head = _read_until(proc.stdout, "using the built-in synthetic scene")
    proc.send_signal(signal.SIGINT)
    code, err = _finish(proc)
    assert code == 130 and "Traceback" not in err and _last_line(err) == "atgs-train: interrupted", err + head
    assert _snapshot(out) == before
    assert not [p for p in cache.rglob("*") if ".tmp-" in p.name], "no half-built scene is left in the cache"


def test_a_checkpoint_path_that_is_not_a_run_is_refused(tmp_path, capsys) -> None:
    from atgs.cli.train import main as train_main

    ckpt = write_tiny_checkpoint(tmp_path / "ckpt.pt")
    before = _snapshot(tmp_path)
    assert train_main(["--out", str(tmp_path), "--resume", "--data", str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("atgs-train: error: ") and "\n" not in err, err
    assert train_main(["--out", str(tmp_path / "new"), "--resume"]) == 2
    assert "not found; start without --resume" in capsys.readouterr().err
    assert _snapshot(tmp_path) == before and ckpt.is_file()
