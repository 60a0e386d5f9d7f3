"""Balanced view sampling over temporal segments and a bounded cache of training images."""

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

    def __init__(self, timeline: Timeline, train_cameras: list[int], generator: torch.Generator) -> None:
        if not train_cameras:
            raise ValueError("no training cameras: every camera is a test camera")
        self.timeline, self.cams, self.gen = timeline, list(train_cameras), generator
        self.segments = [m for m in range(timeline.num_segments) if len(timeline.frames_of_segment(m))]
        self.queue: list[int] = []

    def next(self) -> tuple[int, int]:
        if not self.queue:
            perm = torch.randperm(len(self.segments), generator=self.gen).tolist()
            self.queue = [self.segments[i] for i in perm]
        m = self.queue.pop()
        frames = self.timeline.frames_of_segment(m)
        f = frames[int(torch.randint(len(frames), (1,), generator=self.gen))]
        c = self.cams[int(torch.randint(len(self.cams), (1,), generator=self.gen))]
        return c, f

    def state_dict(self) -> dict:
        return {"queue": torch.tensor(self.queue, dtype=torch.int64)}

    def load_state_dict(self, state: dict) -> None:
        self.queue = [int(x) for x in state["queue"].tolist()]


class ImageCache:
    """LRU cache of uint8 images keyed by (camera, frame), bounded in megabytes, so memory
    stays flat in the sequence length."""

    def __init__(self, load: Callable[[int, int], np.ndarray], max_mb: int) -> None:
        self.load, self.max_bytes = load, max(0, int(max_mb)) * 2**20
        self.items: OrderedDict[tuple[int, int], np.ndarray] = OrderedDict()
        self.bytes = 0

    def get(self, cam: int, frame: int) -> torch.Tensor:
        key = (cam, frame)
        arr = self.items.get(key)
        if arr is None:
            arr = np.array(self.load(cam, frame), dtype=np.uint8, order="C")  # owned, writable
            if arr.nbytes <= self.max_bytes:
                self.items[key] = arr
                self.bytes += arr.nbytes
                while self.bytes > self.max_bytes:
                    _, old = self.items.popitem(last=False)
                    self.bytes -= old.nbytes
        else:
            self.items.move_to_end(key)
        return torch.from_numpy(arr).float() / 255.0
