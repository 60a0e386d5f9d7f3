"""The one wrapper around every command's body, and Ctrl-C as a clean stop.

:func:`run_cli` keeps the promises of the README for all commands (``atgs-train``, ``-prepare``,
``-synth``, ``-eval``, ``-export``, ``-view``, ``-render``): a :class:`~atgs.errors.UserError` (bad input, an
output that may not be replaced, a run that cannot go on) becomes one line
``<command>: error: <message>`` on stderr and exit code 2, never a traceback; Ctrl-C becomes one
line ``<command>: interrupted[: what was kept]`` and exit code 130. Outputs are atomic
(:mod:`atgs.io.atomic`), so an interrupted command leaves nothing half-written.

:func:`stop_on_sigint` lets a long loop (training) finish its current step on the first Ctrl-C,
save, and stop; a second Ctrl-C aborts at once.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator

from atgs.errors import UserError

EXIT_USER_ERROR = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT, what shells report for Ctrl-C


class Interrupted(KeyboardInterrupt):
    """Ctrl-C, after the command saved what it could; the message says what was kept."""


def one_line(text: str) -> str:
    lines = [s.strip() for s in str(text).strip().splitlines() if s.strip()]
    return lines[0] if lines else "unknown error"


def run_cli(prog: str, body: Callable[[], int | None],
            user_errors: tuple[type[BaseException], ...] = (), process: bool = False) -> int:
    """Run ``body()`` and return the process exit code (``body``'s, or 0 when it returns None).
    ``user_errors`` are further exception types that this command reports as user errors.
    ``process``: this is the process's entry point (a console script, ``main(argv=None)``); after
    a Ctrl-C the process then ends here with exit code 130. (Returning 130 is not enough: CPython
    sometimes ends a process whose KeyboardInterrupt was handled by re-raising SIGINT at exit,
    seen as "killed by SIGINT" instead of code 130 in about 1 of 10 interrupted runs here.)"""
    try:
        code = body()
    except (UserError, *user_errors) as e:
        print(f"{prog}: error: {one_line(str(e)) if str(e) else type(e).__name__}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt as e:
        _ignore_further_sigint()  # a second Ctrl-C while the process exits must not print a traceback
        detail = one_line(str(e)) if str(e) else ""
        print(f"{prog}: interrupted" + (f": {detail}" if detail else ""), file=sys.stderr)
        if process:
            _exit_now(EXIT_INTERRUPTED)
        return EXIT_INTERRUPTED
    return 0 if code is None else int(code)


def _exit_now(code: int) -> None:
    """End the process with ``code`` once everything is flushed (outputs were closed by the
    ``finally`` blocks that the KeyboardInterrupt went through)."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)


def _ignore_further_sigint() -> None:
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


class StopRequest:
    """Set by the first Ctrl-C inside :func:`stop_on_sigint`; call it to ask whether to stop."""

    def __init__(self) -> None:
        self.requested = False

    def __call__(self) -> bool:
        return self.requested


@contextlib.contextmanager
def stop_on_sigint(notice: str = "stopping after this step (Ctrl-C again to abort)") -> Iterator[StopRequest]:
    """While in the block the first SIGINT only sets the yielded request (and prints ``notice``
    unless it is empty);
    the loop polls it and stops at a safe point. A second SIGINT raises KeyboardInterrupt.
    The previous handler is restored on exit. Outside the main thread nothing is installed
    (signals go to the main thread) and the request is never set."""
    request = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield request
        return

    def handler(signum: int, frame: object) -> None:
        if request.requested:
            raise KeyboardInterrupt
        request.requested = True
        if notice:
            print(f"\n{notice}", file=sys.stderr, flush=True)

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield request
    finally:
        signal.signal(signal.SIGINT, previous)
