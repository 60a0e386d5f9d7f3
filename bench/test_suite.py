"""The README's test command, timed: the pytest part of `./scripts/test.sh`.

    python bench/test_suite.py                           # the whole suite -> bench/results/test_suite.json
    python bench/test_suite.py --pytest-args tests/test_timeline.py --out /tmp/suite.json   # a subset

Runs `python -m pytest -q -p no:cacheprovider` (this interpreter: run it with the project's
environment) from the repository root, shows pytest's output as it comes, reads the counts from
pytest's summary line and writes them with the wall time, the load average before and after and
the date. A subset run records its arguments (the README row then says so). bench/readme_table.py
turns the JSON into the README row.

Memory: the largest resident size any one process of the run reached (the pytest process or one
it started: the kernel's maximum over the waited-for process tree, what GNU time reports, and the
plugin's figures, since its resets lower the kernel's for the pytest process), and, from the
pytest plugin bench/_suite_memory.py, each test's peak in the pytest process and in its
subprocesses. The tests above MEMORY_LIMIT_MB (4 GB: the suite must pass on an 8 GB machine) and
the largest ones go to the JSON's "memory", under "whole suite" or the pytest arguments of a
re-check; every test's figures to --memory-log. The JSON is merged into --out (keys this run does
not write are kept; --memory-only leaves the README row's counts and time alone).

    python bench/test_suite.py --memory-only --pytest-args tests/test_x.py   # re-check one file's memory
"""

from __future__ import annotations

import json
import os
import platform
import resource
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
MEMORY_LIMIT_MB = 4096  # per process: ./scripts/test.sh passes on an 8 GB machine
PLUGIN = ("-p", "_suite_memory")  # bench/_suite_memory.py
OUTCOMES = ("passed", "failed", "skipped", "errors", "xfailed", "xpassed", "deselected", "warnings")


@dataclass
class SuiteArgs:
    pytest_args: tuple[str, ...] = ()
    """Extra pytest arguments, e.g. a test file for a quick check (recorded in the JSON)."""
    out: Path = ROOT / "bench" / "results" / "test_suite.json"
    memory_log: Path = Path("/tmp/atgs-suite-memory.jsonl")
    """Every test's memory figures, one JSON line each (bench/_suite_memory.py)."""
    top: int = 12
    """Tests listed in the JSON by their peak (the pytest process's, and their subprocesses')."""
    memory_only: bool = False
    """Record only the memory figures (under "memory", by what ran), not the counts and the time
    of the README row: a re-check of some files, or a run on a loaded machine."""


def summary_counts(line: str) -> dict[str, int]:
    """{'passed': 509, 'skipped': 6, ...} from pytest's last line, e.g. '509 passed, 6 skipped in 115.2s'."""
    counts = dict.fromkeys(OUTCOMES, 0)
    for n, word in re.findall(r"(\d+) (passed|failed|skipped|errors?|xfailed|xpassed|deselected|warnings?)", line):
        counts[word if word in counts else word + "s"] += int(n)
    return counts


def is_summary(line: str) -> bool:
    return re.search(r"\bin [\d.]+s\b", line) is not None and re.search(r"\d+ \w+", line) is not None


def memory_summary(log: Path, largest_process_mb: float, top: int) -> dict:
    """The run's memory: the largest process, the tests whose pytest process or subprocess peaked
    highest, and the tests above MEMORY_LIMIT_MB (per process)."""
    tests = [json.loads(line) for line in log.read_text().splitlines() if line.strip()] if log.is_file() else []

    def child_peak(t: dict) -> float:
        return max((c["peak_mb"] for c in t["children"]), default=0.0)

    def row(t: dict) -> dict:
        biggest = max(t["children"], key=lambda c: c["peak_mb"], default=None)
        return {"test": t["test"], "pytest_peak_mb": t["peak_mb"], "growth_mb": round(t["after_mb"] - t["before_mb"], 1),
                "subprocesses": len(t["children"]), "largest_subprocess_mb": child_peak(t),
                **({"largest_subprocess": biggest["cmd"]} if biggest else {})}

    over = [row(t) for t in tests if max(t["peak_mb"], child_peak(t)) > MEMORY_LIMIT_MB]
    by_pytest = sorted(tests, key=lambda t: -t["peak_mb"])[:top]
    by_child = sorted((t for t in tests if t["children"]), key=lambda t: -child_peak(t))[:top]
    pytest_peak = max((t["peak_mb"] for t in tests), default=0.0)
    subprocess_peak = max((child_peak(t) for t in tests), default=0.0)
    # (the plugin's resets of the high-water mark lower the kernel's figure for the pytest process)
    largest = max(largest_process_mb, pytest_peak, subprocess_peak)
    return {"limit_mb_per_process": MEMORY_LIMIT_MB, "largest_process_mb": round(largest, 1),
            "pytest_process_peak_mb": pytest_peak, "largest_subprocess_mb": subprocess_peak,
            "tests_measured": len(tests), "tests_over_limit": over,
            "largest_in_pytest_process": [row(t) for t in by_pytest],
            "largest_subprocesses": [row(t) for t in by_child]}


def run_pytest(args: SuiteArgs) -> tuple[list[str], int, float, list[float]]:
    """pytest's output lines, its exit code, the wall seconds and the load average before."""
    cmd = [sys.executable, *COMMAND, *PLUGIN, *args.pytest_args]
    env = {**os.environ, "ATGS_SUITE_MEMORY": str(args.memory_log),
           "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT / "bench"), os.environ.get("PYTHONPATH")]))}
    args.memory_log.unlink(missing_ok=True)
    load_before = list(os.getloadavg())
    t0 = time.perf_counter()
    lines: list[str] = []
    with subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) as proc:
        for line in proc.stdout:  # pytest's own progress (dots and percentages) is the progress display
            print(line, end="", flush=True)
            lines.append(line.strip())
    return lines, proc.returncode, time.perf_counter() - t0, load_before


def record(result: dict, args: SuiteArgs, run: dict, memory: dict) -> dict:
    """``result`` (the JSON as it was) with this run: its memory under "memory" by what ran ("whole
    suite", or the pytest arguments of a re-check), and, unless --memory-only, its counts and time
    at the top (the README row)."""
    scope = " ".join(args.pytest_args) or "whole suite"
    result = {**result, "memory": {**result.get("memory", {}), scope: {**run, **memory}}}
    if not args.memory_only:
        result |= {"command": "python " + " ".join(COMMAND), "pytest_args": list(args.pytest_args), **run}
    return result


def main(args: SuiteArgs) -> int:
    lines, code, seconds, load_before = run_pytest(args)
    summary = next((ln.strip("= ") for ln in reversed(lines) if is_summary(ln)), None)
    if summary is None:
        print(f"bench/test_suite.py: pytest printed no summary line (exit code {code}); "
              f"{args.out} left as it was", file=sys.stderr)
        return 2
    largest_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss  # (Linux: kB)
    memory = memory_summary(args.memory_log, largest_kb / 1024, args.top)
    run = {"summary": summary, **summary_counts(summary), "exit_code": code, "seconds": seconds,
           "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                       "loadavg_before": load_before, "loadavg_after": list(os.getloadavg())},
           "commit": git_commit(ROOT), "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())}
    old = json.loads(args.out.read_text()) if args.out.is_file() else {}
    write_json_atomic(args.out, record(old, args, run, memory))
    print(f"wrote {args.out}: {summary} ({seconds:.0f} s wall); largest process {memory['largest_process_mb']:.0f} MB, "
          f"{len(memory['tests_over_limit'])} tests above {MEMORY_LIMIT_MB} MB; the README row: "
          "python bench/readme_table.py")
    return 0 if code == 0 else 1


if __name__ == "__main__":
    sys.exit(main(tyro.cli(SuiteArgs)))
