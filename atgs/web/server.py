"""The static HTTP server of a web export (``atgs-serve``, and the browser tests' server).

Browsers refuse ``fetch`` from ``file://`` pages, so the player needs a server; any static one
does. This one serves files as they are (a chunk's gzip bytes as application/octet-stream: the
player inflates them itself), with the MIME types ES modules need, and logs failures only.
"""

from __future__ import annotations

import errno
import socket
import sys
from functools import partial
from http import HTTPStatus
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from atgs.errors import UserError

# Module scripts must come as JavaScript (browsers refuse others); the rest as the player expects.
MIME_TYPES = {".js": "text/javascript", ".mjs": "text/javascript", ".bin": "application/octet-stream",
              ".json": "application/json", ".html": "text/html", ".css": "text/css", ".png": "image/png"}


class ServeError(UserError):
    """An address that cannot be listened on (or, for atgs-serve, a folder that is no web export)."""


class WebFolderHandler(SimpleHTTPRequestHandler):
    extensions_map = {**SimpleHTTPRequestHandler.extensions_map, **MIME_TYPES}

    def log_request(self, code: int | str = "-", size: int | str = "-") -> None:
        """Log failures only: a playing video fetches a chunk every few frames."""
        status = int(code) if isinstance(code, (int, HTTPStatus)) or str(code).isdigit() else 0
        if status >= 400:
            super().log_request(code, size)


class _QuietServer(ThreadingHTTPServer):
    def handle_error(self, request, client_address) -> None:
        """A browser that leaves a page mid-download closes its connections: not an error."""
        if not isinstance(sys.exc_info()[1], (BrokenPipeError, ConnectionResetError)):
            super().handle_error(request, client_address)


class _Server6(_QuietServer):
    address_family = socket.AF_INET6


def make_server(folder: Path, host: str, port: int) -> ThreadingHTTPServer:
    """A server of ``folder`` bound to ``host``:``port`` (0: a free one; ``server_address`` says
    which), not serving yet: call ``serve_forever`` (and ``server_close`` when done)."""
    if not 0 <= port <= 65535:
        raise ServeError(f"--port {port}: must be within 0..65535 (0 picks a free port)")
    handler = partial(WebFolderHandler, directory=str(Path(folder).resolve()))
    server_class = _Server6 if ":" in host else _QuietServer
    try:
        return server_class((host, port), handler)
    except OSError as e:
        if e.errno == errno.EADDRINUSE:
            raise ServeError(f"port {port} is in use; pick another with --port") from None
        if e.errno == errno.EACCES:
            raise ServeError(f"port {port}: permission denied (ports below 1024 need privileges); "
                             "pick another with --port") from None
        raise ServeError(f"--host {host}: cannot listen there ({e.strerror or e})") from None


def page_url(server: ThreadingHTTPServer, host: str, page: str = "index.html") -> str:
    """The address a browser on this machine opens ``page`` at."""
    port = server.server_address[1]
    shown = {"": "127.0.0.1", "0.0.0.0": "127.0.0.1", "::": "[::1]"}.get(host, f"[{host}]" if ":" in host else host)
    return f"http://{shown}:{port}/{page}"
