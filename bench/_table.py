"""Markdown tables made of the benchmarks' results files (bench/results/*.json), and the
table between a page's `<!-- bench:NAME:start/end -->` markers.

A table is a list of :class:`Row`: one function per row reads one results file and returns its
:class:`Cells`; the table's ``line`` function lays the cells out. Every number comes from a JSON
field. A row whose results file is missing says which bench script to run; a file that cannot
be used is a :class:`TableError` naming it and the script that rewrites it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, NamedTuple

from _docs import markers  # bench/_docs.py (the script's own folder is on sys.path)


class TableError(Exception):
    """A results file or a page cannot be used; the message is the one line to print."""


class Cells(NamedTuple):
    details: str  # what exactly was measured (numbers from the JSON), after the row's label
    run: str  # date and machine load of the run
    measured: str
    verdict: str = ""  # against the row's target


@dataclass(frozen=True)
class Row:
    result: str  # bench/results/<result>.json
    script: str  # the bench script that writes it
    label: str
    target: str
    cells: Callable[[Any], Cells]


def span(values: Iterable[float], fmt: str = "{:.1f}") -> str:
    """The values' range, 'lo-hi', or one figure when both ends print alike."""
    values = list(values)
    lo, hi = fmt.format(min(values)), fmt.format(max(values))
    return lo if lo == hi else f"{lo}-{hi}"


def count(n: float) -> str:
    """20k, 1M: how many Gaussians or anchors."""
    return f"{n / 1e6:.3g}M" if n >= 1e6 else f"{n / 1e3:.0f}k"


def run_of(date: str | None, loads: Iterable[float] = ()) -> str:
    """Day of the run and the range of its 1-minute load averages."""
    loads = list(loads)
    if not date:
        return f"date not recorded, load {span(loads)}" if loads else "date and load not recorded"
    return f"{date[:10]}, load {span(loads)}" if loads else f"{date[:10]}, load not recorded"


def one_minute(*records: dict, keys: tuple[str, str] = ("loadavg_before", "loadavg_after")) -> list[float]:
    """The 1-minute load averages recorded before and after each record's run."""
    return [rec[k][0] for rec in records for k in keys]


def reached(ok: bool, why: str = "") -> str:
    return ("**reached**" if ok else "**not reached**") + (f" ({why})" if why else "")


def load_result(folder: Path, row: Row) -> Any | None:
    path = folder / f"{row.result}.json"
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise TableError(f"{path}: not readable JSON ({e}); rerun bench/{row.script}") from None


def cells_of(row: Row, result: Any, path: Path) -> Cells:
    """The row's cells; a results file without the fields the row reads is a TableError."""
    try:
        return row.cells(result)
    except (KeyError, IndexError, StopIteration, TypeError, ValueError) as e:
        why = f"no field {e}" if isinstance(e, KeyError) else str(e) or type(e).__name__
        raise TableError(f"{path}: unusable for the row '{row.label}' ({why}); rerun `bench/{row.script}`") from None


def markdown_row(cells: Iterable[str]) -> str:
    return "| " + " | ".join(cell.replace("|", "\\|") for cell in cells) + " |"


def build_table(results: Path, head: str, rows: Iterable[Row],
                line: Callable[[Row, Cells | None], str]) -> str:
    """The Markdown table ``rows`` give from the results folder: ``head`` (its header and
    separator lines), then ``line(row, cells)`` per row (cells None: no results file)."""
    if not results.is_dir():
        raise TableError(f"{results}: no such results folder (the bench scripts write bench/results/)")
    lines = [head]
    loaded: dict[str, Any] = {}
    for row in rows:
        if row.result not in loaded:
            loaded[row.result] = load_result(results, row)
        result = loaded[row.result]
        lines.append(line(row, None if result is None else cells_of(row, result, results / f"{row.result}.json")))
    return "\n".join(lines)


def table_in(page: Path, name: str) -> str:
    """The table now between the page's bench:NAME markers."""
    start, end = markers(name)
    try:
        text = page.read_text()
    except OSError as e:
        raise TableError(f"{page}: cannot read it ({e.strerror})") from None
    if start not in text or end not in text:
        raise TableError(f"{page}: no {start} ... {end} markers around the results table; add them")
    return text.split(start, 1)[1].split(end, 1)[0].strip("\n")
