"""The one wrapper around every command's body, and Ctrl-C as a clean stop.

:func:`run_cli` keeps the promises of the README for all commands (``atgs-train``, ``-prepare``,
``-synth``, ``-eval``, ``-view``, ``-render``): a :class:`~atgs.errors.UserError` (bad input, an
output that may not be replaced, a run that cannot go on) becomes one line
``<command>: error: <message>`` on stderr and exit code 2, never a traceback; Ctrl-C becomes one
line ``<command>: interrupted[: what was kept]`` and exit code 130. Outputs are atomic
(:mod:`atgs.io.atomic`), so an interrupted command leaves nothing half-written.

:func:`stop_on_sigint` lets a long loop (training) finish its current step on the first Ctrl-C,
save, and stop; a second Ctrl-C aborts at once.
"""

from __future__ import annotations

import contextlib
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
            user_errors: tuple[type[BaseException], ...] = ()) -> int:
    """Run ``body()`` and return the process exit code (``body``'s, or 0 when it returns None).
    ``user_errors`` are further exception types that this command reports as user errors."""
    try:
        code = body()
    except (UserError, *user_errors) as e:
        print(f"{prog}: error: {one_line(str(e)) if str(e) else type(e).__name__}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt as e:
        detail = one_line(str(e)) if str(e) else ""
        print(f"{prog}: interrupted" + (f": {detail}" if detail else ""), file=sys.stderr)
        return EXIT_INTERRUPTED
    return 0 if code is None else int(code)


class StopRequest:
    """Set by the first Ctrl-C inside :func:`stop_on_sigint`; call it to ask whether to stop."""

    def __init__(self) -> None:
        self.requested = False

    def __call__(self) -> bool:
        return self.requested


@contextlib.contextmanager
def stop_on_sigint(notice: str = "stopping after this step (Ctrl-C again to abort)") -> Iterator[StopRequest]:
    """While in the block the first SIGINT only sets the yielded request (and prints ``notice``);
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
        print(f"\n{notice}", file=sys.stderr, flush=True)

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield request
    finally:
        signal.signal(signal.SIGINT, previous)
