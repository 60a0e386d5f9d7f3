"""How many threads torch's CPU ops use inside a block (the one place that changes it).

Decoding, packing and sorting a frame are many small memory-bound passes; with torch's OpenMP
threads they stall whenever another core is busy. On this project's 2-core machine: packing 50k
Gaussians took 330-450 ms with two threads and 3.5-28 ms with one at load 8 (the viewer), and
decoding a 21k-Gaussian frame of a ``cpu-fast`` model 422-665 ms with two and 24-26 ms with one
at load 7 (``atgs-export``). OpenMP's thread count is per calling thread, so other threads
(another decode, the UI) keep theirs.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch


@contextmanager
def torch_threads(threads: int = 1) -> Iterator[None]:
    """Run the enclosed torch CPU ops with ``threads`` intra-op threads, then restore."""
    before = torch.get_num_threads()
    if before == threads:
        yield
        return
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)
