"""atgs-prepare SRC --out DIR: multi-view videos (N3DV, COLMAP frame folders, EasyVolcap, or
plain videos/images without poses) -> a prepared ATGS scene (see docs/data.md)."""

from __future__ import annotations

import sys
import tyro

from atgs.data.errors import DataError
from atgs.data.prepare import PrepareConfig, prepare


def main(argv: list[str] | None = None) -> int:
    args = tyro.cli(PrepareConfig, args=argv, description=__doc__)
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
