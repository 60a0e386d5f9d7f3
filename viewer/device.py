"""Where the viewer decodes, packs and sorts: ``--device auto|cpu|cuda``.

Everything downstream (viewer.packing, viewer.sorting) is written with torch ops that run on
either device, so the CPU tests exercise the code that runs on CUDA. A source that can move
itself (has ``to(device)``) decodes on the device; one that cannot decodes on the CPU and its
Gaussians are moved to the device for packing and sorting.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch

from atgs import device as atgs_device
from atgs.viewer.errors import ViewerError

DEVICE_NAMES = atgs_device.DEVICE_NAMES
DeviceName = atgs_device.DeviceName


def resolve_device(name: str) -> torch.device:
    """"auto" -> CUDA when torch sees a CUDA device, else the CPU; "cuda" without one is an error
    (atgs.device: the rule atgs-train uses too; playback needs no gsplat)."""
    try:
        return atgs_device.resolve_device(name, need_gsplat=False)
    except atgs_device.DeviceError as e:
        raise ViewerError(str(e)) from None


def place_source(source, device: torch.device):
    """The source moved to ``device`` when it supports ``to(device)``, else the source as it is
    (it then decodes on the CPU and :func:`viewer.source.decode_frame` moves its output)."""
    mover = getattr(source, "to", None)
    if device.type == "cpu" or mover is None:
        return source
    moved = mover(device)
    return source if moved is None else moved


@contextmanager
def cpu_threads(device: torch.device, threads: int = 1) -> Iterator[None]:
    """Run the enclosed torch ops with ``threads`` intra-op threads when ``device`` is the CPU.

    Packing and sorting are a few memory-bound passes; with torch's two OpenMP threads they
    stall whenever the other core is busy (llvmpipe, the decode thread, other programs): packing
    50k Gaussians took 330-450 ms with two threads and 3.5-28 ms with one at load 8 on this
    2-core machine. OpenMP's thread count is per calling thread, so this leaves the model's
    decode (other calls, other threads) alone."""
    before = torch.get_num_threads()
    if device.type != "cpu" or before == threads:
        yield
        return
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)
