"""The README's test command, timed: the pytest part of `./scripts/test.sh`.

    python bench/test_suite.py                           # the whole suite -> bench/results/test_suite.json
    python bench/test_suite.py --pytest-args tests/test_timeline.py --out /tmp/suite.json   # a subset

Runs `python -m pytest -q -p no:cacheprovider` (this interpreter: run it with the project's
environment) from the repository root, shows pytest's output as it comes, reads the counts from
pytest's summary line and writes them with the wall time, the load average before and after and
the date. A subset run records its arguments (the README row then says so). bench/readme_table.py
turns the JSON into the README row.
"""

from __future__ import annotations

import os
import platform
import re
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import tyro
from _docs import git_commit, write_json_atomic  # bench/_docs.py (the script's own folder is on sys.path)

ROOT = Path(__file__).resolve().parent.parent
COMMAND = ("-m", "pytest", "-q", "-p", "no:cacheprovider")
OUTCOMES = ("passed", "failed", "skipped", "errors", "xfailed", "xpassed", "deselected", "warnings")


@dataclass
class SuiteArgs:
    pytest_args: tuple[str, ...] = ()
    """Extra pytest arguments, e.g. a test file for a quick check (recorded in the JSON)."""
    out: Path = ROOT / "bench" / "results" / "test_suite.json"


def summary_counts(line: str) -> dict[str, int]:
    """{'passed': 509, 'skipped': 6, ...} from pytest's last line, e.g. '509 passed, 6 skipped in 115.2s'."""
    counts = dict.fromkeys(OUTCOMES, 0)
    for n, word in re.findall(r"(\d+) (passed|failed|skipped|errors?|xfailed|xpassed|deselected|warnings?)", line):
        counts[word if word in counts else word + "s"] += int(n)
    return counts


def is_summary(line: str) -> bool:
    return re.search(r"\bin [\d.]+s\b", line) is not None and re.search(r"\d+ \w+", line) is not None


def main(args: SuiteArgs) -> int:
    cmd = [sys.executable, *COMMAND, *args.pytest_args]
    load_before = os.getloadavg()
    t0 = time.perf_counter()
    lines: list[str] = []
    with subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) as proc:
        for line in proc.stdout:  # pytest's own progress (dots and percentages) is the progress display
            print(line, end="", flush=True)
            lines.append(line.strip())
    seconds = time.perf_counter() - t0
    summary = next((ln.strip("= ") for ln in reversed(lines) if is_summary(ln)), None)
    if summary is None:
        print(f"bench/test_suite.py: pytest printed no summary line (exit code {proc.returncode}); "
              f"{args.out} left as it was", file=sys.stderr)
        return 2
    result = {
        "command": "python " + " ".join(COMMAND), "pytest_args": list(args.pytest_args), "summary": summary,
        **summary_counts(summary), "exit_code": proc.returncode, "seconds": seconds,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "loadavg_before": list(load_before), "loadavg_after": list(os.getloadavg())},
        "commit": git_commit(ROOT), "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
    }
    write_json_atomic(args.out, result)
    print(f"wrote {args.out}: {summary} ({seconds:.0f} s wall); the README row: python bench/readme_table.py")
    return 0 if proc.returncode == 0 else 1


if __name__ == "__main__":
    sys.exit(main(tyro.cli(SuiteArgs)))
