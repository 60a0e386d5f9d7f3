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
from atgs.threads import torch_threads
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
    """Run the enclosed torch ops with ``threads`` intra-op threads when ``device`` is the CPU
    (:func:`atgs.threads.torch_threads`: packing and sorting stall with two OpenMP threads when
    the other core is busy, 330-450 ms against 3.5-28 ms for 50k Gaussians at load 8 here)."""
    if device.type != "cpu":
        yield
        return
    with torch_threads(threads):
        yield
