"""A benchmark's results: stamped (when, at what load, at which commit), written as JSON, and its
table written into a docs page between `<!-- bench:NAME:start/end -->` markers."""

from __future__ import annotations

import os
import subprocess
import time
from pathlib import Path

from atgs.io.atomic import write_json_atomic as _write_json, write_text_atomic


REPO = Path(__file__).resolve().parent.parent


def markers(name: str) -> tuple[str, str]:
    return f"<!-- bench:{name}:start -->", f"<!-- bench:{name}:end -->"


def update_docs_table(path: Path, name: str, table: str, create_section: str | None = None) -> bool:
    """Replace the text between the markers (atomically). Without markers: append a section
    titled ``create_section`` if given, else leave the file alone and return False."""
    start, end = markers(name)
    text = path.read_text() if path.exists() else ""
    if start not in text or end not in text:
        if create_section is None:
            print(f"{path}: no bench:{name} markers; table not written")
            return False
        text = text.rstrip() + f"\n\n## {create_section}\n\n{start}\n{end}\n"
    head, rest = text.split(start, 1)
    _, tail = rest.split(end, 1)
    write_text_atomic(path, f"{head}{start}\n{table}\n{end}{tail}")
    return True


def write_json_atomic(path: Path, data) -> None:
    """Results JSON (indent 2, as the committed bench/results files)."""
    _write_json(path, data, indent=2)


def git_commit(repo: Path) -> str:
    """The repository's short HEAD commit, recorded with a result ("unknown" outside git)."""
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=repo, capture_output=True,
                              text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def today() -> str:
    return time.strftime("%Y-%m-%d")


def utc_now() -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())


def loadavg() -> list[float]:
    """The machine's 1, 5 and 15-minute load averages: how much else ran beside a timing."""
    return list(os.getloadavg())


def run_stamp(load: bool = True) -> dict:
    """The fields that end a run's results row: its load average at the end (``load``), the
    commit measured and the day."""
    return {**({"loadavg": loadavg()} if load else {}), "commit": git_commit(REPO), "date": today()}


def publish(result, json_out: Path, table: str, docs: Path | None, name: str) -> None:
    """The end of every benchmark: results JSON (atomic), the table on screen and in the docs."""
    write_json_atomic(json_out, result)
    print(f"wrote {json_out}")
    print(table)
    if docs is not None:
        update_docs_table(docs, name, table)
