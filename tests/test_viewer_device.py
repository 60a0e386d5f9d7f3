"""--device auto|cpu|cuda: resolution and moving a source (atgs/viewer/device.py)."""

from __future__ import annotations

import pytest
import torch

from atgs.viewer.device import place_source, resolve_device
from atgs.viewer.errors import ViewerError
from atgs.viewer.source import SyntheticSource, decode_frame


def test_resolve_device() -> None:
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(ViewerError, match="--device gpu"):
        resolve_device("gpu")
    if torch.cuda.is_available():
        assert resolve_device("cuda").type == "cuda"
    else:
        with pytest.raises(ViewerError, match="no CUDA device"):
            resolve_device("cuda")


def test_place_source_moves_what_can_move() -> None:
    src = SyntheticSource(num_gaussians=50, frames=2)
    assert place_source(src, torch.device("cpu")) is src

    class Fixed:  # a source without to(): stays where it is
        pass

    fixed = Fixed()
    assert place_source(fixed, torch.device("meta")) is fixed
    moved = place_source(src, torch.device("meta"))  # any non-CPU device: the source's own to()
    assert moved is not src and moved.device == "meta"
    assert moved.gaussians_at_frame(0).means.device.type == "meta"


def test_decode_frame_on_the_cpu_is_the_default() -> None:
    src = SyntheticSource(num_gaussians=50, frames=2)
    for device in (None, "cpu", torch.device("cpu")):
        packed = decode_frame(src, 1, device)
        assert packed.device.type == "cpu" and len(packed) == 50 and packed.frame == 1


def test_cpu_threads_is_scoped_to_cpu_work() -> None:
    from atgs.viewer.device import cpu_threads

    before = torch.get_num_threads()
    with cpu_threads(torch.device("cpu"), threads=1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
    with cpu_threads(torch.device("meta"), threads=1):  # another device: torch's setting is left alone
        assert torch.get_num_threads() == before
    with pytest.raises(RuntimeError):
        with cpu_threads(torch.device("cpu"), threads=1):
            raise RuntimeError("restored even on errors")
    assert torch.get_num_threads() == before
