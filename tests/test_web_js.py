"""The web player's JavaScript unit tests (tests/js/*.test.mjs: chunk, stream, camera, sort),
run with Node's built-in test runner so that the Python suite runs them too."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_player_modules_pass_node_tests() -> None:
    node = shutil.which("node")
    if node is None:
        pytest.skip("no Node.js on PATH (./scripts/test.sh installs Debian's nodejs)")
    major = int(subprocess.run([node, "--version"], capture_output=True, text=True).stdout.strip().lstrip("v").split(".")[0])
    if major < 20:
        pytest.skip(f"Node.js {major}: the player's tests need 20 or newer (DecompressionStream, node --test on a folder)")
    # the files by name (what `node --test tests/js/` runs on Node 20; later Nodes read a folder argument as a glob)
    files = sorted(str(p.relative_to(ROOT)) for p in (ROOT / "tests" / "js").glob("*.test.mjs"))
    assert files, "no tests/js/*.test.mjs"
    run = subprocess.run([node, "--test", *files], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, f"node --test tests/js/ failed:\n{run.stdout[-6000:]}\n{run.stderr[-2000:]}"
    assert "# fail 0" in run.stdout
