"""atgs-prepare SRC --out DIR: multi-view videos (N3DV, COLMAP frame folders, EasyVolcap, or
plain videos/images without poses) -> a prepared ATGS scene (see docs/data.md)."""

from __future__ import annotations

import sys

import tyro

from atgs.data.prepare import PrepareConfig, prepare
from atgs.io.cli import run_cli


def main(argv: list[str] | None = None) -> int:
    args = tyro.cli(PrepareConfig, args=argv, description=__doc__)

    def body() -> None:
        print(f"prepared scene written to {prepare(args)}")

    return run_cli("atgs-prepare", body, process=argv is None)


if __name__ == "__main__":
    sys.exit(main())
