"""The results tables, regenerated from the benchmarks' results (bench/results/*.json): the
README's headline (at most eight rows: quality, training time, player speed, test suite) and
the full table with every measurement, its target and whether it is reached (docs/benchmarks.md).

    python bench/readme_table.py            # rewrite both tables
    python bench/readme_table.py --check    # exit 1 if either table is not what the results give
    python bench/readme_table.py --results DIR --readme FILE --benchmarks FILE

The rows: bench/_headline.py and bench/_full_table.py (one function per row reads one results
file); the table mechanism: bench/_table.py. Each table sits between its page's
`<!-- bench:NAME:start/end -->` markers (README.md: readme, docs/benchmarks.md: benchmarks).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import _full_table as full  # bench/ (the script's own folder is on sys.path)
import _headline as headline
import tyro
from _docs import update_docs_table
from _table import TableError, build_table, table_in

ROOT = Path(__file__).resolve().parent.parent


@dataclass
class TableArgs:
    results: Path = ROOT / "bench" / "results"
    """Folder of the benchmarks' JSON results."""
    readme: Path = headline.PAGE
    """The page of the headline table."""
    benchmarks: Path = full.PAGE
    """The page of the full table."""
    check: bool = False
    """Change nothing; exit 1 if a page's table differs from what the results give."""


def tables(args: TableArgs) -> list[tuple[Path, str, str]]:
    """(page, marker name, the table the results give) of each table."""
    return [(args.readme, headline.NAME, build_table(args.results, headline.HEAD, headline.ROWS, headline.line)),
            (args.benchmarks, full.NAME, build_table(args.results, full.HEAD, full.ROWS, full.line))]


def main(args: TableArgs) -> int:
    try:
        made = tables(args)
        current = [table_in(page, name) for page, name, _ in made]
    except TableError as e:
        print(e, file=sys.stderr)
        return 2
    stale = [(page, now, table) for (page, _, table), now in zip(made, current) if now != table]
    if args.check:
        if not stale:
            return 0
        page, now, table = stale[0]
        first = next((n for o, n in zip(now.splitlines(), table.splitlines()) if o != n), "the row count")
        also = f" (and {', '.join(str(p) for p, _, _ in stale[1:])})" if len(stale) > 1 else ""
        print(f"{page}{also}: the results table differs from {args.results} (first: {first[:70]}...); "
              "regenerate it with python bench/readme_table.py", file=sys.stderr)
        return 1
    for (page, name, table), now in zip(made, current):
        update_docs_table(page, name, table)
        print(f"{page}: results table {'unchanged' if now == table else 'updated'}")
    return 0


if __name__ == "__main__":
    sys.exit(main(tyro.cli(TableArgs)))
