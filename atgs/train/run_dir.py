"""The files of a training run in its output directory, and when they change.

    OUT/ckpt.pt         the resumable checkpoint (atomic)
    OUT/config.json     preset, data, device and the configuration of the last checkpoint (atomic)
    OUT/train_log.csv   one row per step, up to the last checkpoint
    OUT/result.json     the final summary (atomic)
    OUT/eval/           the final evaluation (atgs.eval, atomic)

Promise (README): nothing in OUT changes until this process has written its first checkpoint.
Until then the config and the log rows wait in memory, so a refused, failed or interrupted
start leaves an existing run byte-identical. The first checkpoint commits the run: config.json
is written and train_log.csv is rewritten to hold the rows this run continues from (a resumed
run keeps the old rows up to its checkpoint's step) and the new ones; a fresh run that replaces
an earlier run (``--overwrite``) also drops that run's result.json and eval/. Later checkpoints append the rows logged since, so the log
always ends at the step of ckpt.pt or later. config.json is rewritten with every checkpoint from
the configuration it holds, so it says what ran: the schedule a time budget sized, the background
and camera exposure resolved from the scene (a resumed run keeps the preset and data it names).

A run has an identity, ``run_id``, written into every checkpoint and config.json from the first
one on: a resumed run keeps it, a fresh run has a new one. Under torchrun it is the start's own
(:func:`start_id`), so that a worker restarted after a failure tells a checkpoint of the run it
started from the one an ``--overwrite`` start replaces (atgs.cli.train.restarted_run).
"""

from __future__ import annotations

import csv
import io
import json
import os
import shutil
import uuid
from pathlib import Path

from atgs.checkpoint import read_checkpoint, save_checkpoint
from atgs.io.atomic import write_json_atomic, write_text_atomic

LOG_FIELDS = ("step", "loss", "psnr", "anchors", "gaussians", "seconds", "skipped", "eval_psnr", "eval_ssim")


def start_id() -> str | None:
    """The identity of this start under torchrun, the same in the workers it restarts after a
    failure: its rendezvous id (a fresh uuid per launch on one machine, ``--rdzv-id`` on
    several). None outside torchrun, or on several machines without ``--rdzv-id`` ("none")."""
    launch = os.environ.get("TORCHELASTIC_RUN_ID", "")
    return None if launch in ("", "none") else launch


def new_run_id() -> str:
    """The identity of a run that starts now: this start's (so that its restarts know their own
    checkpoints), else a random one."""
    return start_id() or str(uuid.uuid4())


def run_id_of(ckpt: Path) -> str | None:
    """The run a checkpoint belongs to (None: written before runs had an identity). Memory-mapped:
    reads the pickle, not the tables."""
    run_id = read_checkpoint(ckpt, mmap=True).get("run_id")
    return run_id if isinstance(run_id, str) else None


class RunDir:
    def __init__(self, out: str | Path, resume_step: int | None = None, run_id: str | None = None) -> None:
        """``resume_step``: the step of the checkpoint a resumed run continues from (None: fresh);
        ``run_id``: the identity that checkpoint carries (None: a new one, as a fresh run's)."""
        self.out = Path(out)
        self.resume_step = resume_step
        self.run_id = run_id if isinstance(run_id, str) and run_id else new_run_id()
        self.replaces_run = resume_step is None and self.ckpt_path.exists()
        self.committed = False
        # config.json less the configuration: None writes no config.json (a run started in code)
        self._header: dict | None = self._old_header() if resume_step is not None else None
        self._rows: list[dict] = []

    @property
    def ckpt_path(self) -> Path:
        return self.out / "ckpt.pt"

    def stage_config(self, header: dict) -> None:
        """What config.json holds besides the configuration (preset, data, device), written with
        each checkpoint; a resumed run's entries update the file's."""
        self._header = {**(self._header or {}), **header}

    def log(self, row: dict) -> None:
        self._rows.append(row)

    def save_checkpoint(self, payload: dict) -> Path:
        save_checkpoint(self.ckpt_path, {**payload, "run_id": self.run_id})
        if self._header is not None:
            write_json_atomic(self.out / "config.json", {**self._header, "run_id": self.run_id,
                                                         "model": payload["model_config"],
                                                         "train": payload["train_config"]})
        if self.committed:
            self._append_rows()
        else:
            self._commit()
        return self.ckpt_path

    def write_result(self, result: dict) -> Path:
        path = self.out / "result.json"
        write_json_atomic(path, result)
        return path

    # --- internals ---------------------------------------------------------------------------------
    def _commit(self) -> None:
        log = self.out / "train_log.csv"
        kept = self._old_rows(log) if self.resume_step is not None else []
        if self.replaces_run:
            (self.out / "result.json").unlink(missing_ok=True)
            shutil.rmtree(self.out / "eval", ignore_errors=True)
        write_text_atomic(log, _csv_text(kept + self._rows, header=True))
        self._rows.clear()
        self.committed = True

    def _append_rows(self) -> None:
        if self._rows:
            with open(self.out / "train_log.csv", "a", newline="") as fh:
                fh.write(_csv_text(self._rows, header=False))
            self._rows.clear()

    def _old_header(self) -> dict | None:
        try:
            old = json.loads((self.out / "config.json").read_text())
        except (OSError, ValueError):  # none (a run started in code) or unreadable: not rewritten
            return None
        return {k: v for k, v in old.items() if k not in ("model", "train")} if isinstance(old, dict) else None

    def _old_rows(self, log: Path) -> list[dict]:
        """Rows of the log being continued, up to the resumed checkpoint's step (a run killed
        after its last checkpoint logged steps that the resumed run does again)."""
        if not log.is_file():
            return []
        with open(log, newline="") as fh:
            return [r for r in csv.DictReader(fh) if r.get("step", "").isdigit() and int(r["step"]) <= self.resume_step]


def _csv_text(rows: list[dict], header: bool) -> str:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=LOG_FIELDS, lineterminator="\r\n")
    if header:
        writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()
