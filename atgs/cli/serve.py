"""``atgs-serve DIR``: serve a web export (``atgs-export CKPT --out DIR --format web``) on a local
HTTP server (:mod:`atgs.web.server`) and print the player's address. Bad input is one line on
stderr and exit code 2 (atgs.io.cli); Ctrl-C stops it."""

from __future__ import annotations

import sys
import threading
import webbrowser
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

from atgs.io.cli import run_cli
from atgs.web.server import ServeError, make_server, page_url

PAGE = "index.html"
MANIFEST = "stream/manifest.json"


@dataclass
class ServeArgs:
    """Serve a folder written by atgs-export --format web on a local HTTP server and print the
    address of its player page (Ctrl-C stops)."""

    dir: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="DIR")]
    """The exported folder (index.html, player/, stream/)."""
    port: int = 8000
    """TCP port; 0 picks a free one (the address printed says which)."""
    host: str = "127.0.0.1"
    """Address to listen on (0.0.0.0: every network interface; other machines can then connect)."""
    open_browser: bool = False
    """Open the player page in the default web browser."""


def check_web_folder(folder: Path) -> None:
    if not folder.is_dir():
        raise ServeError(f"{folder}: {'not a folder' if folder.exists() else 'not found'}; "
                         "pass the folder written by atgs-export --format web")
    if not (folder / PAGE).is_file() or not (folder / MANIFEST).is_file():
        raise ServeError(f"{folder}: not a web export (no {PAGE} and {MANIFEST}); write one with: "
                         "atgs-export CKPT --out DIR --format web")


def main(argv: list[str] | None = None) -> int:
    args = tyro.cli(ServeArgs, args=argv, prog="atgs-serve")

    def body() -> None:
        check_web_folder(args.dir)
        server = make_server(args.dir, args.host, args.port)
        url = page_url(server, args.host, PAGE)
        try:
            print(f"atgs-serve: serving {args.dir} at {url} (Ctrl-C to stop)", flush=True)
            if args.open_browser:
                threading.Thread(target=webbrowser.open, args=(url,), daemon=True).start()
            server.serve_forever()
        finally:
            server.server_close()

    return run_cli("atgs-serve", body, process=argv is None)


if __name__ == "__main__":
    sys.exit(main())
