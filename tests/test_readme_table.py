"""The README's headline table and docs/benchmarks.md's full table are what
bench/readme_table.py makes of bench/results/*.json: --check passes on the committed files and
fails as soon as one result changes, until the tables are regenerated. The README opens with
the two commands CI and a newcomer run. No benchmark runs here; the edits are made to copies
in a temporary folder."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
BENCH = REPO / "bench"


@pytest.fixture
def table(monkeypatch: pytest.MonkeyPatch):
    """bench/readme_table.py as a module (it imports bench/_docs.py as its neighbour)."""
    monkeypatch.syspath_prepend(str(BENCH))
    spec = importlib.util.spec_from_file_location("readme_table", BENCH / "readme_table.py")
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "readme_table", module)  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


@pytest.fixture
def copies(tmp_path: Path) -> tuple[Path, Path, Path]:
    """A copy of bench/results, of README.md and of docs/benchmarks.md."""
    results = tmp_path / "results"
    shutil.copytree(BENCH / "results", results)
    readme = tmp_path / "README.md"
    shutil.copy(REPO / "README.md", readme)
    benchmarks = tmp_path / "benchmarks.md"
    shutil.copy(REPO / "docs" / "benchmarks.md", benchmarks)
    return results, readme, benchmarks


def check(table, results: Path, readme: Path, benchmarks: Path, write: bool = False) -> int:
    return table.main(table.TableArgs(results=results, readme=readme, benchmarks=benchmarks, check=not write))


def outside_table(page: Path, name: str) -> list[str]:
    text = page.read_text()
    head, rest = text.split(f"<!-- bench:{name}:start -->")
    return [head, rest.split(f"<!-- bench:{name}:end -->")[1]]


def table_rows(page: Path, name: str) -> list[str]:
    """The rows of the page's table between its bench:NAME markers (header and separator left out)."""
    inside = page.read_text().split(f"<!-- bench:{name}:start -->")[1].split(f"<!-- bench:{name}:end -->")[0]
    return [ln for ln in inside.strip().splitlines()[2:]]


def test_committed_tables_are_what_the_committed_results_give() -> None:
    proc = subprocess.run([sys.executable, str(BENCH / "readme_table.py"), "--check"], cwd=REPO,
                          capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert proc.returncode == 0, proc.stderr


def test_a_changed_result_fails_the_check_until_the_table_is_regenerated(table, copies, capsys) -> None:
    results, readme, benchmarks = copies
    raster = json.loads((results / "rasterizer.json").read_text())
    first = raster["results"][0]
    assert (first["n"], first["width"], first["height"]) == tuple(raster["target"][k] for k in ("n", "width", "height"))
    new_ms = first["cpu"]["forward_ms"] + 7.0
    first["cpu"]["forward_ms"] = new_ms
    (results / "rasterizer.json").write_text(json.dumps(raster))
    shown = f"| {new_ms:.1f} ms / {first['cpu']['forward_backward_ms']:.1f} ms"
    around = outside_table(benchmarks, "benchmarks")
    readme_before = readme.read_text()

    assert check(table, results, readme, benchmarks) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(benchmarks) in err and "rasterizer" in err
    assert str(readme) not in err  # the headline has no rasterizer row: only the full table is stale
    assert shown not in benchmarks.read_text()

    assert check(table, results, readme, benchmarks, write=True) == 0
    assert shown in benchmarks.read_text()
    assert outside_table(benchmarks, "benchmarks") == around
    assert readme.read_text() == readme_before
    assert check(table, results, readme, benchmarks) == 0


def test_a_missing_result_names_the_script_to_run(table, copies) -> None:
    results, readme, benchmarks = copies
    (results / "decode.json").unlink()
    assert check(table, results, readme, benchmarks) == 1
    assert check(table, results, readme, benchmarks, write=True) == 0
    row = next(ln for ln in benchmarks.read_text().splitlines() if ln.startswith("| model decode"))
    assert "| not measured (run `bench/decode.py`) |" in row


def test_the_demo_rows_show_the_figures_the_demo_printed(table, copies, capsys) -> None:
    results, readme, benchmarks = copies
    printed = ("atgs-train: done, 4321 steps in 1187 s; test PSNR 23.46 dB, SSIM 0.7891; "
               "checkpoint /tmp/atgs-bench-demo/demo/ckpt.pt")
    demo = {"command": "atgs-train --out runs/demo", "printed": printed, "psnr": 23.4567, "ssim": 0.78912,
            "eval_views": 240, "steps": 4321, "train_seconds": 1187.2, "wall_seconds": 1500.0, "budget_seconds": 1200.0,
            "machine": {"cpus": 2, "loadavg_before": [2.0, 2.0, 2.0], "loadavg_after": [2.5, 2.0, 2.0]},
            "date": "2026-11-24"}
    (results / "demo.json").write_text(json.dumps(demo))
    assert check(table, results, readme, benchmarks) == 1
    capsys.readouterr()
    assert check(table, results, readme, benchmarks, write=True) == 0
    row = next(ln for ln in benchmarks.read_text().splitlines() if ln.startswith("| the README's main job"))
    assert "test PSNR 23.46 dB, SSIM 0.7891" in row and "4321 steps" in row
    headline = table_rows(readme, "readme")
    built_in = next(ln for ln in headline if "built-in synthetic scene" in ln)
    assert "| 23.46 dB PSNR, SSIM 0.789 |" in built_in and "(`bench/demo.py`, 2026-11-24)" in built_in
    pace = next(ln for ln in headline if ln.startswith("| Training time, CPU"))
    assert f"4,321 steps at {1187.2 / 4321:.2f} s" in pace and "20-minute budget" in pace

    demo["psnr"] = 24.0  # the stored figure no longer what was printed
    (results / "demo.json").write_text(json.dumps(demo))
    before = readme.read_text(), benchmarks.read_text()
    assert check(table, results, readme, benchmarks, write=True) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "demo.json" in err
    assert (readme.read_text(), benchmarks.read_text()) == before


def test_a_corrupt_result_is_a_one_line_error_and_changes_nothing(table, copies, capsys) -> None:
    results, readme, benchmarks = copies
    (results / "viewer.json").write_text('{"per_count": [')
    before = readme.read_text(), benchmarks.read_text()
    assert check(table, results, readme, benchmarks, write=True) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "viewer.json" in err and "bench/viewer.py" in err
    assert (readme.read_text(), benchmarks.read_text()) == before


def test_the_headline_is_short_and_the_full_table_keeps_every_row_and_verdict(table) -> None:
    import _full_table
    import _headline

    readme, benchmarks = REPO / "README.md", REPO / "docs" / "benchmarks.md"
    headline = table_rows(readme, "readme")
    assert 0 < len(headline) == len(_headline.ROWS) <= _headline.MAX_ROWS == 8
    full = table_rows(benchmarks, "benchmarks")
    assert len(full) == len(_full_table.ROWS)
    # the targets' verdicts stay with the full table, as the results say: the demo misses 30 dB
    demo = json.loads((BENCH / "results" / "demo.json").read_text())
    main_job = next(ln for ln in full if ln.startswith("| the README's main job"))
    assert ("**not reached**" in main_job) == (demo["psnr"] < _full_table.PSNR_DB)
    assert main_job.endswith(" |") and f"{_full_table.PSNR_DB} dB" in main_job.rsplit("|", 2)[1]
    assert not any("reached**" in ln for ln in headline)


def test_the_readme_opens_with_what_it_does_the_two_commands_a_picture_and_the_headline() -> None:
    text = (REPO / "README.md").read_text()
    first_block = re.search(r"```bash\n(.*?)```", text, re.S)
    commands = [ln.split("#")[0].strip() for ln in first_block.group(1).strip().splitlines()]
    assert commands == ["./scripts/demo.sh", "./scripts/test.sh"]
    ci = [ln.strip() for ln in (REPO / ".ci" / "run").read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    assert ci[-1] == "./scripts/test.sh"  # the README's test command is what CI runs
    assert all((REPO / c[2:]).is_file() for c in commands)

    picture = re.search(r"!\[[^\]]*\]\(([^)]+)\)", text)
    table_start = text.index("<!-- bench:readme:start -->")
    assert picture.start() < table_start and text[picture.end():table_start].count("\n## ") == 1
    assert (REPO / picture.group(1)).is_file()
    assert text.index(first_block.group(0)) < picture.start()
    first_screen = text[:text.index("<!-- bench:readme:end -->")]
    assert first_screen.count("\n") <= 40  # what it does, the commands, the picture and the table

    linked = set(re.findall(r"docs/[\w./-]+\.(?:md|png|json)", text))
    assert "docs/benchmarks.md" in linked and "docs/install.md" in linked
    assert not [p for p in linked if not (REPO / p).is_file()]
