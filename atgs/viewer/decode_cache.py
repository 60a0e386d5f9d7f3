"""Background decoding of upcoming frames into an LRU cache.

The UI thread calls :meth:`DecodeCache.request` with the frames it wants (most urgent first)
and :meth:`DecodeCache.get`, which never blocks: a frame that is not decoded yet is simply
``None`` and the player keeps showing the last ready frame.

``capacity`` frames are always kept; beyond that, decoded frames stay while they fit in
``keep_bytes``, so that a sequence whose decoding is slower than real time plays every frame
from the second loop on (a trained 'cpu' model: ~60 ms per frame to decode, ~3.5 MB per frame).
:meth:`DecodeCache.prefetch` lets the worker fill that budget while nothing wanted is missing
(e.g. while the player is paused on its first frame), so that it can play every frame at once.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from atgs.viewer.packing import PackedGaussians


@dataclass
class CacheStats:
    hits: int = 0
    misses: int = 0
    decoded: int = 0
    evicted: int = 0


class DecodeCache:
    """One worker thread decoding ``decode(frame)`` into at most ``capacity`` cached frames."""

    def __init__(self, decode: Callable[[int], PackedGaussians], capacity: int = 6,
                 pinned: dict[int, PackedGaussians] | None = None, keep_bytes: int = 0) -> None:
        """``pinned``: frames decoded up front (``--preload``); never evicted, never decoded again.
        ``keep_bytes``: decoded frames beyond ``capacity`` are kept while their total size fits."""
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        if keep_bytes < 0:
            raise ValueError(f"keep_bytes must be >= 0, got {keep_bytes}")
        self._decode = decode
        self.capacity = capacity
        self.keep_bytes = keep_bytes
        self._bytes = 0
        self._last_bytes = 0  # size of the last decoded frame: the estimate of the next one
        self._fill: list[int] = []
        self._fill_evictions = 0
        self._cond = threading.Condition()
        self._pinned = dict(pinned or {})
        self._cache: OrderedDict[int, PackedGaussians] = OrderedDict()
        self._wanted: list[int] = []
        self._failed: dict[int, str] = {}
        self._busy: int | None = None
        self._stop = False
        self.stats = CacheStats()
        self.last_error: str | None = None
        self._thread = threading.Thread(target=self._run, name="atgs-decode", daemon=True)
        self._thread.start()

    # --- UI thread (never blocks on decoding) ------------------------------------------------
    def request(self, frames: Sequence[int]) -> None:
        """Frames wanted soon, most urgent first; replaces the previous request."""
        wanted = list(dict.fromkeys(int(f) for f in frames))[: self.capacity]
        with self._cond:
            self._wanted = wanted
            self._cond.notify()

    def prefetch(self, frames: Sequence[int]) -> None:
        """Frames to decode, in this order, whenever no wanted frame is missing, while they fit
        in ``keep_bytes``. Filling stops for good at the first eviction (the budget is full and
        playback now needs the room), so it never evicts what it decoded itself."""
        with self._cond:
            self._fill = list(dict.fromkeys(int(f) for f in frames))
            self._fill_evictions = self.stats.evicted
            self._cond.notify()

    def get(self, frame: int) -> PackedGaussians | None:
        with self._cond:
            p = self._pinned.get(frame)
            if p is not None:
                self.stats.hits += 1
                return p
            p = self._cache.get(frame)
            if p is None:
                self.stats.misses += 1
                return None
            self._cache.move_to_end(frame)
            self.stats.hits += 1
            return p

    def snapshot(self) -> dict[int, PackedGaussians]:
        """The decoded frames right now (a copy of the index; the frames are shared)."""
        with self._cond:
            return {**self._cache, **self._pinned}

    def cached_frames(self) -> list[int]:
        with self._cond:
            return list(self._cache) + [f for f in self._pinned if f not in self._cache]

    @property
    def busy_frame(self) -> int | None:
        return self._busy

    # --- blocking helpers for headless rendering and tests ----------------------------------------
    def wait_for(self, frame: int, timeout: float | None = None) -> PackedGaussians | None:
        """Request ``frame`` (keeping the other wanted frames) and wait until it is decoded."""
        with self._cond:
            if frame in self._pinned:
                return self._pinned[frame]
            if frame not in self._wanted:
                self._wanted = [frame] + self._wanted[: self.capacity - 1]
                self._cond.notify_all()
            ok = self._cond.wait_for(
                lambda: frame in self._cache or frame in self._failed or self._stop, timeout=timeout
            )
            if ok and frame in self._failed:
                raise RuntimeError(self._failed[frame])
            if frame in self._cache:
                self._cache.move_to_end(frame)
            return self._cache.get(frame)

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Wait until the worker has nothing left to do (no wanted or prefetch frame to decode,
        none in progress); False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: self._stop or (self._busy is None and self._next_job() is None),
                                       timeout=timeout)

    def close(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._thread.join(timeout=10.0)

    def __enter__(self) -> "DecodeCache":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- worker ----------------------------------------------------------------------------
    def _next_job(self) -> int | None:
        for f in self._wanted:
            if f not in self._cache and f not in self._failed and f not in self._pinned:
                return f
        if (self._fill and self.stats.evicted == self._fill_evictions
                and self._bytes + max(self._last_bytes, 1) <= self.keep_bytes):
            for f in self._fill:
                if f not in self._cache and f not in self._failed and f not in self._pinned:
                    return f
        return None

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._stop or self._next_job() is not None)
                if self._stop:
                    return
                frame = self._next_job()
                self._busy = frame
            assert frame is not None
            try:
                packed = self._decode(frame)
                error = None
            except Exception as exc:  # reported to the UI, never kills the worker
                packed, error = None, f"decoding frame {frame} failed: {type(exc).__name__}: {exc}"
            with self._cond:
                self._busy = None
                if packed is None:
                    self._failed[frame] = error or "unknown error"
                    self.last_error = error
                else:
                    self._cache[frame] = packed
                    self._last_bytes = packed_bytes(packed)
                    self._bytes += self._last_bytes
                    self._cache.move_to_end(frame)
                    self.stats.decoded += 1
                    self._evict()
                self._cond.notify_all()

    @property
    def cached_bytes(self) -> int:
        """Bytes held by the (unpinned) decoded frames."""
        return self._bytes

    def _evict(self) -> None:
        keep = set(self._wanted)
        while len(self._cache) > self.capacity and self._bytes > self.keep_bytes:
            victim = next((f for f in self._cache if f not in keep), None)
            if victim is None:
                victim = next(iter(self._cache))
            self._bytes -= packed_bytes(self._cache.pop(victim))
            self.stats.evicted += 1


def packed_bytes(p: PackedGaussians) -> int:
    """Memory of one decoded frame (vertex records, SH, sort and cull inputs)."""
    return p.nbytes
