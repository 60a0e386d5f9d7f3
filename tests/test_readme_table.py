"""The README's results table is what bench/readme_table.py makes of bench/results/*.json:
--check passes on the committed files and fails as soon as one result changes, until the table
is regenerated. No benchmark runs here; the edits are made to copies in a temporary folder."""

from __future__ import annotations

import importlib.util
import json
import os
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
def copies(tmp_path: Path) -> tuple[Path, Path]:
    """A copy of bench/results and of README.md."""
    results = tmp_path / "results"
    shutil.copytree(BENCH / "results", results)
    readme = tmp_path / "README.md"
    shutil.copy(REPO / "README.md", readme)
    return results, readme


def check(table, results: Path, readme: Path, write: bool = False) -> int:
    return table.main(table.TableArgs(results=results, readme=readme, check=not write))


def outside_table(readme: Path) -> list[str]:
    text = readme.read_text()
    head, rest = text.split("<!-- bench:readme:start -->")
    return [head, rest.split("<!-- bench:readme:end -->")[1]]


def test_committed_readme_table_is_what_the_committed_results_give() -> None:
    proc = subprocess.run([sys.executable, str(BENCH / "readme_table.py"), "--check"], cwd=REPO,
                          capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert proc.returncode == 0, proc.stderr


def test_a_changed_result_fails_the_check_until_the_table_is_regenerated(table, copies, capsys) -> None:
    results, readme = copies
    raster = json.loads((results / "rasterizer.json").read_text())
    first = raster["results"][0]
    assert (first["n"], first["width"], first["height"]) == tuple(raster["target"][k] for k in ("n", "width", "height"))
    new_ms = first["cpu"]["forward_ms"] + 7.0
    first["cpu"]["forward_ms"] = new_ms
    (results / "rasterizer.json").write_text(json.dumps(raster))
    shown = f"| {new_ms:.1f} ms / {first['cpu']['forward_backward_ms']:.1f} ms"
    around = outside_table(readme)

    assert check(table, results, readme) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(readme) in err and "rasterizer" in err
    assert shown not in readme.read_text()

    assert check(table, results, readme, write=True) == 0
    assert shown in readme.read_text()
    assert outside_table(readme) == around
    assert check(table, results, readme) == 0


def test_a_missing_result_names_the_script_to_run(table, copies) -> None:
    results, readme = copies
    (results / "decode.json").unlink()
    assert check(table, results, readme) == 1
    assert check(table, results, readme, write=True) == 0
    row = next(ln for ln in readme.read_text().splitlines() if ln.startswith("| model decode"))
    assert "| not measured (run `bench/decode.py`) |" in row


def test_the_demo_row_shows_the_figures_the_demo_printed(table, copies, capsys) -> None:
    results, readme = copies
    printed = ("atgs-train: done, 4321 steps in 1187 s; test PSNR 23.46 dB, SSIM 0.7891; "
               "checkpoint /tmp/atgs-bench-demo/demo/ckpt.pt")
    demo = {"command": "atgs-train --out runs/demo", "printed": printed, "psnr": 23.4567, "ssim": 0.78912,
            "eval_views": 240, "steps": 4321, "train_seconds": 1187.2, "wall_seconds": 1500.0,
            "machine": {"loadavg_before": [2.0, 2.0, 2.0], "loadavg_after": [2.5, 2.0, 2.0]}, "date": "2026-11-24"}
    (results / "demo.json").write_text(json.dumps(demo))
    assert check(table, results, readme, write=True) == 0
    row = next(ln for ln in readme.read_text().splitlines() if ln.startswith("| the README's main job"))
    assert "test PSNR 23.46 dB, SSIM 0.7891" in row and "4321 steps" in row

    demo["psnr"] = 24.0  # the stored figure no longer what was printed
    (results / "demo.json").write_text(json.dumps(demo))
    before = readme.read_text()
    assert check(table, results, readme, write=True) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "demo.json" in err
    assert readme.read_text() == before


def test_a_corrupt_result_is_a_one_line_error_and_changes_nothing(table, copies, capsys) -> None:
    results, readme = copies
    (results / "viewer.json").write_text('{"per_count": [')
    before = readme.read_text()
    assert check(table, results, readme, write=True) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "viewer.json" in err and "bench/viewer.py" in err
    assert readme.read_text() == before
