"""pytest plugin of bench/test_suite.py: each test's peak resident memory, and its subprocesses'.

Loaded with ``-p _suite_memory`` (bench/ on PYTHONPATH) when $ATGS_SUITE_MEMORY names a file;
one JSON line per test is appended to it as the test ends (a crash keeps what came before).

- The pytest process: the kernel's high-water mark (VmHWM) is reset to the current size before
  each test (writing 5 to /proc/self/clear_refs) and read after its teardown, so ``peak_mb`` is
  the most the process held during that test, set-up of module fixtures included (they land on
  the module's first test); ``before_mb`` / ``after_mb`` are its size around the test (growth is
  what the test left behind: caches, fixtures, fragmentation).
- Subprocesses (the CLIs, torchrun and its workers): a thread reads the high-water mark of every
  descendant every 0.2 s; the last reading before a process ends is its peak within 0.2 s.
"""

from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path

import pytest

LOG = os.environ.get("ATGS_SUITE_MEMORY")
SAMPLE_S = 0.2


def status_mb(pid: int | str = "self") -> dict[str, float]:
    """VmRSS and VmHWM of a process in MB ({} once it is gone)."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return {}
    out = {}
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            out[key] = int(value.split()[0]) / 1024
    return out


def reset_peak() -> bool:
    """Set this process's VmHWM to its current size (Linux 4.0+); False where not allowed."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def descendants(root: int) -> list[int]:
    """Every living process below ``root`` (read from each process's parent in /proc/*/stat)."""
    parent = {}
    for entry in os.scandir("/proc"):
        if entry.name.isdigit():
            try:
                stat = Path(f"/proc/{entry.name}/stat").read_text()
            except OSError:
                continue
            parent[int(entry.name)] = int(stat.rsplit(")", 1)[1].split()[1])  # (the name may hold spaces)
    found, frontier = [], [root]
    while frontier:
        p = frontier.pop()
        kids = [c for c, pp in parent.items() if pp == p]
        found += kids
        frontier += kids
    return found


def command(pid: int) -> str:
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return "?"
    return " ".join(a.decode(errors="replace") for a in argv[:6] if a)[:160]


class ChildWatch(threading.Thread):
    """Peak memory of this process's descendants, per test (``take`` returns and clears them)."""

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.lock = threading.Lock()
        self.seen: dict[int, dict] = {}

    def run(self) -> None:
        me = os.getpid()
        while True:
            for pid in descendants(me):
                peak = status_mb(pid).get("VmHWM")
                if peak is None:
                    continue
                with self.lock:
                    rec = self.seen.setdefault(pid, {"pid": pid, "cmd": command(pid), "peak_mb": 0.0})
                    rec["peak_mb"] = max(rec["peak_mb"], round(peak, 1))
            time.sleep(SAMPLE_S)

    def take(self) -> list[dict]:
        with self.lock:
            out, self.seen = sorted(self.seen.values(), key=lambda r: -r["peak_mb"]), {}
        return out


_watch: ChildWatch | None = None


def pytest_configure(config: pytest.Config) -> None:
    global _watch
    if LOG and _watch is None:
        _watch = ChildWatch()
        _watch.start()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None):
    if not LOG:
        yield
        return
    before = status_mb().get("VmRSS", 0.0)
    reset = reset_peak()
    t0 = time.perf_counter()
    yield
    now = status_mb()
    record = {"test": item.nodeid, "peak_mb": round(now.get("VmHWM", 0.0), 1), "before_mb": round(before, 1),
              "after_mb": round(now.get("VmRSS", 0.0), 1), "peak_is_per_test": reset,
              "seconds": round(time.perf_counter() - t0, 2), "children": _watch.take() if _watch else []}
    with open(LOG, "a") as f:
        f.write(json.dumps(record) + "\n")
