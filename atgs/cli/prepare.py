"""atgs-prepare SRC --out DIR: multi-view videos (N3DV, COLMAP frame folders, EasyVolcap, or
plain videos/images without poses) -> a prepared ATGS scene (see docs/data.md)."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

from atgs.data.errors import DataError
from atgs.data.prepare import PrepareConfig, prepare


@dataclass(frozen=True)
class PrepareArgs(PrepareConfig):
    src: Annotated[Path, tyro.conf.Positional] = Path()
    """Dataset directory (N3DV, COLMAP frame folders, EasyVolcap, plain videos or image folders)."""
    out: Path = Path()
    """Output directory (required); written atomically, never half-written."""


def main(argv: list[str] | None = None) -> int:
    args = tyro.cli(PrepareArgs, args=argv, description=__doc__)
    if args.out == Path() or args.src == Path():
        print("error: give a source directory and --out DIR", file=sys.stderr)
        return 2
    try:
        out = prepare(args)
    except DataError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted; nothing was written", file=sys.stderr)
        return 130
    print(f"prepared scene written to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
