"""The web player's JavaScript unit tests (tests/js/*.test.mjs: chunk, stream, window, fetcher, camera, sort, options,
controls),
run with Node's built-in test runner so that the Python suite runs them too."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_player_modules_pass_node_tests() -> None:
    # a failure, not a skip: the player's JavaScript would go untested (./scripts/test.sh installs Node.js)
    node = shutil.which("node")
    assert node is not None, "no Node.js on PATH: run ./scripts/test.sh, or sudo apt-get install nodejs"
    version = subprocess.run([node, "--version"], capture_output=True, text=True).stdout.strip()
    major = int(version.lstrip("v").split(".")[0])
    # 18: node --test and a global DecompressionStream (Debian 12's nodejs is 18.19)
    assert major >= 18, f"Node.js {version}: the player's tests need 18 or newer"
    # the files by name (what `node --test tests/js/` runs on Node 20; later Nodes read a folder argument as a glob)
    files = sorted(str(p.relative_to(ROOT)) for p in (ROOT / "tests" / "js").glob("*.test.mjs"))
    assert files, "no tests/js/*.test.mjs"
    run = subprocess.run([node, "--test", *files], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, f"node --test tests/js/ failed:\n{run.stdout[-6000:]}\n{run.stderr[-2000:]}"
    assert "# fail 0" in run.stdout
