"""The torch floor is what the code needs (torch.serialization.skip_data: 2.5), pyproject.toml asks
for it, and ``import atgs`` refuses an older torch in one line (the installed torch is not
changed: its version is patched)."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import pytest
import torch

import atgs

REPO = Path(__file__).resolve().parent.parent


@pytest.mark.parametrize("version", ["2.4.1+cpu", "2.4.0", "1.13.1", "2.0.0a0+gitabc"])
def test_import_refuses_an_older_torch_in_one_line_with_the_fix(monkeypatch, version) -> None:
    monkeypatch.setattr(torch, "__version__", version)
    with pytest.raises(ImportError) as e:
        atgs.check_torch()
    message = str(e.value)
    assert "\n" not in message and f"torch {version} is installed" in message, message
    assert message.startswith("atgs needs torch>=2.5") and message.endswith("pip install 'torch>=2.5'"), message


@pytest.mark.parametrize("version", ["2.5.0", "2.5.1+cu124", "2.6.0.dev20250101", "2.13.0+cpu", "3.0.0", "weird"])
def test_import_accepts_the_floor_and_newer(monkeypatch, version) -> None:
    monkeypatch.setattr(torch, "__version__", version)
    atgs.check_torch()  # ("weird": a version it cannot read is not refused)


def test_pyproject_asks_for_the_floor_the_import_checks() -> None:
    deps = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    floors = [re.fullmatch(r"torch>=(\d+)\.(\d+)", d.replace(" ", "")) for d in deps if d.startswith("torch")]
    assert len(floors) == 1 and floors[0], deps
    assert tuple(map(int, floors[0].groups())) == atgs.TORCH_MIN


def test_the_installed_torch_has_what_sets_the_floor() -> None:
    assert callable(torch.serialization.skip_data) and hasattr(torch._C.PyTorchFileReader, "get_record_offset")
