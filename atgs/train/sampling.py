"""Balanced view sampling over temporal segments and a bounded cache of training images.

The sampler draws on the CPU (its generator's device) whatever the training device, so a seed
picks the same views everywhere; it returns Python ints. The image cache keeps uint8 images on
the training device (see :class:`ImageCache`)."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable

import numpy as np
import torch

from atgs.timeline import Timeline


class SegmentSampler:
    """Yields (camera index, frame). Segments are visited in shuffled rounds so that every
    temporal grid gets the same number of views; the frame is uniform within the segment and
    the camera uniform over the training cameras. All randomness comes from ``generator``."""

    def __init__(self, timeline: Timeline, train_cameras: list[int], generator: torch.Generator,
                 segments: range | None = None) -> None:
        """``segments``: draw from these only (default all; a worker of the time partition)."""
        if not train_cameras:
            raise ValueError("no training cameras: every camera is a test camera")
        self.timeline, self.cams, self.gen = timeline, list(train_cameras), generator
        among = range(timeline.num_segments) if segments is None else segments
        self.segments = [m for m in among if len(timeline.frames_of_segment(m))]
        self.queue: list[int] = []

    def next(self) -> tuple[int, int]:
        cams, f = self.next_views(1)
        return cams[0], f

    def next_views(self, cameras: int) -> tuple[list[int], int]:
        """A frame and ``cameras`` distinct training cameras that see it (all of them when
        there are fewer); with one camera the draws are those of earlier versions."""
        if not self.queue:
            perm = torch.randperm(len(self.segments), generator=self.gen, device=self.gen.device).tolist()
            self.queue = [self.segments[i] for i in perm]
        m = self.queue.pop()
        frames = self.timeline.frames_of_segment(m)
        f = frames[int(torch.randint(len(frames), (1,), generator=self.gen, device=self.gen.device))]
        if cameras <= 1:
            return [self.cams[int(torch.randint(len(self.cams), (1,), generator=self.gen, device=self.gen.device))]], f
        pick = torch.randperm(len(self.cams), generator=self.gen, device=self.gen.device)[:cameras].tolist()
        return [self.cams[i] for i in pick], f

    def state_dict(self) -> dict:
        return {"queue": torch.tensor(self.queue, dtype=torch.int64, device="cpu")}  # saved with the checkpoint

    def load_state_dict(self, state: dict) -> None:
        """(Of a sampler over other segments: the queued ones this one draws from.)"""
        self.queue = [int(x) for x in state["queue"].tolist() if int(x) in self.segments]


class ImageCache:
    """LRU cache of uint8 images keyed by (camera, frame), bounded in megabytes, so memory
    stays flat in the sequence length.

    The images are kept on ``device`` (uint8, a quarter of float32): a cached image costs no
    host-to-device copy and no synchronisation per step, and the float conversion runs on the
    device. A miss (decode from disk) copies the image once. Pinned host memory would spare
    device memory but copy every step; ``max_mb`` bounds the device memory used."""

    def __init__(self, load: Callable[[int, int], np.ndarray], max_mb: int,
                 device: torch.device | str = "cpu") -> None:
        self.load, self.max_bytes = load, max(0, int(max_mb)) * 2**20
        self.device = torch.device(device)
        self.items: OrderedDict[tuple[int, int], torch.Tensor] = OrderedDict()
        self.bytes = 0

    def get(self, cam: int, frame: int) -> torch.Tensor:
        """The image as float32 (H, W, 3) in [0, 1] on the cache's device."""
        key = (cam, frame)
        img = self.items.get(key)
        if img is None:
            arr = np.array(self.load(cam, frame), dtype=np.uint8, order="C")  # owned, writable
            img = torch.from_numpy(arr).to(self.device)  # the CPU: the array itself, no copy
            if arr.nbytes <= self.max_bytes:
                self.items[key] = img
                self.bytes += arr.nbytes
                while self.bytes > self.max_bytes:
                    _, old = self.items.popitem(last=False)
                    self.bytes -= old.numel()
        else:
            self.items.move_to_end(key)
        return img.float() / 255.0
