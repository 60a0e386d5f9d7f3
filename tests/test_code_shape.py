"""The trainer reads as training (issue 51): no function of atgs/train/trainer.py or of the
partition strategies (atgs/train/partition/) is longer than 60 lines, and the trainer holds no
branch on workers (the partition object decides). Counted with ``ast`` from the source."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LONGEST = 60
CHECKED = [ROOT / "atgs/train/trainer.py", *sorted((ROOT / "atgs/train/partition").glob("*.py"))]


def long_functions(path: Path, longest: int = LONGEST) -> list[str]:
    """``name (lines)`` of each function or method in ``path`` longer than ``longest`` lines
    (decorators and docstring included)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            first = min([node.lineno] + [d.lineno for d in node.decorator_list])
            lines = node.end_lineno - first + 1
            if lines > longest:
                out.append(f"{node.name} ({lines})")
    return out


def test_the_counter_sees_a_long_function(tmp_path: Path) -> None:
    body = "\n".join(f"    x{i} = {i}" for i in range(LONGEST))
    src = tmp_path / "m.py"
    src.write_text(f"def short():\n    return 1\n\n\n@staticmethod\ndef long():\n{body}\n")
    assert long_functions(src) == [f"long ({LONGEST + 2})"]


def test_no_function_of_the_trainer_or_the_partitions_is_longer_than_60_lines() -> None:
    assert len(CHECKED) > 5, "the partition package"
    long = {p.relative_to(ROOT).as_posix(): long_functions(p) for p in CHECKED}
    assert not {k: v for k, v in long.items() if v}, long


def test_the_trainer_asks_its_partition_instead_of_branching_on_workers() -> None:
    """No attribute of workers, crews, time slices or time groups is read in the trainer."""
    tree = ast.parse((ROOT / "atgs/train/trainer.py").read_text())
    names = {"workers", "crew", "part", "timed", "time_groups", "time_rank"}
    read = sorted({n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute) and n.attr in names
                   and isinstance(n.value, ast.Name) and n.value.id in ("self", "tr")})
    assert read == [], read
