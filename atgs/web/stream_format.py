"""The chunk files of a web export (docs/web.md, "A chunk file"): the one owner of their layout in
Python.

:func:`encode_chunk` turns F frames of Gaussians with stable model ids into one chunk's gzip bytes
(:func:`quantize_chunk`, then :func:`pack_chunk`); :func:`decode_chunk` is the slow, plain
reference reader the tests check the writer (and the docs' promises) with. The browser's reader
is atgs/web/player/chunk.js.
"""

from __future__ import annotations

import gzip
import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

MAGIC = b"ATGC"
VERSION = 1
# magic, version, F, G, S, position min (3), position max (3), log-scale lo, hi
HEADER = struct.Struct("<4sHHII3f3f2f")
MAX_FRAMES = 0xFFFF  # F is a u16
MAX_GAUSSIANS = 0xFFFFFFFF  # G is a u32
GZIP_LEVEL = 9
POSITION_STEPS = 0xFFFF  # u16 positions: min + q / 65535 * (max - min)
LOG_SCALE_STEPS = 0xFF
ROTATION_STEPS = 127  # i8 quaternion components: round(127 q / |q|)
UNIT_STEPS = 0xFF  # opacity and colour: q / 255
MIN_SCALE = 1e-30  # log() of a zero standard deviation would be -inf


@dataclass(frozen=True)
class Field:
    name: str
    components: int
    dtype: np.dtype


# The record's fields in file order (docs/web.md's table).
FIELDS = (
    Field("position", 3, np.dtype("<u2")),
    Field("log_scale", 3, np.dtype("u1")),
    Field("rotation", 4, np.dtype("i1")),
    Field("opacity", 1, np.dtype("u1")),
    Field("colour", 3, np.dtype("u1")),
)
RECORD_BYTES = sum(f.components * f.dtype.itemsize for f in FIELDS)  # 17 byte planes a Gaussian
assert HEADER.size == 48 and RECORD_BYTES == 17


class ChunkFormatError(ValueError):
    """Bytes that are not a chunk this version writes (bad magic or version, truncated, sizes
    that do not add up)."""


@dataclass
class StreamFrame:
    """One frame's n Gaussians as the exporter hands them over (float arrays)."""

    ids: np.ndarray  # (n,) distinct model ids: the same Gaussian has the same id in every frame
    means: np.ndarray  # (n, 3)
    scales: np.ndarray  # (n, 3) linear standard deviations
    quats: np.ndarray  # (n, 4) (w, x, y, z), any norm
    opacities: np.ndarray  # (n,)
    colors: np.ndarray  # (n, 3) linear RGB


@dataclass
class Records:
    """Quantized records, one array per field of :data:`FIELDS` shaped (..., n, components) in
    the field's dtype (the leading axes: frames, where there are several)."""

    position: np.ndarray
    log_scale: np.ndarray
    rotation: np.ndarray
    opacity: np.ndarray
    colour: np.ndarray

    def arrays(self) -> list[np.ndarray]:
        return [getattr(self, f.name) for f in FIELDS]

    def select(self, index) -> "Records":
        """The records at ``index`` of the Gaussian axis (the second to last)."""
        return Records(*(a[..., index, :] for a in self.arrays()))


@dataclass
class QuantizedChunk:
    """A chunk before packing: the G Gaussians in file order (static first) in each of F frames."""

    ids: np.ndarray  # (G,) model ids in file order
    static: int  # S: the first S Gaussians are static
    records: Records  # arrays (F, G, components)
    position_min: np.ndarray  # (3,) float32, as stored
    position_max: np.ndarray
    log_scale_lo: np.float32
    log_scale_hi: np.float32

    @property
    def num_frames(self) -> int:
        return int(self.records.position.shape[0])

    @property
    def num_gaussians(self) -> int:
        return int(self.ids.shape[0])


@dataclass
class DecodedFrame:
    """One frame of a chunk as the reference reader gives it: the G Gaussians in file order."""

    means: np.ndarray  # (G, 3) float32
    scales: np.ndarray  # (G, 3) float32, linear standard deviations
    quats: np.ndarray  # (G, 4) float32, q / 127 as stored (normalized when drawn)
    opacities: np.ndarray  # (G,) float32, 0 where the Gaussian is absent
    colors: np.ndarray  # (G, 3) float32
    records: Records  # the quantized integers, arrays (G, components)


@dataclass
class ChunkFrames:
    """What :func:`decode_chunk` read: the header's numbers and every frame."""

    gaussians: int  # G
    static: int  # S
    position_min: np.ndarray  # (3,) float32
    position_max: np.ndarray
    log_scale_lo: float
    log_scale_hi: float
    frames: list[DecodedFrame]


# --- writing -------------------------------------------------------------------------------------


def encode_chunk(frames: Sequence[StreamFrame]) -> bytes:
    """The gzip bytes of a chunk holding ``frames`` (1 to 65535 of them)."""
    return pack_chunk(quantize_chunk(frames))


def quantize_chunk(frames: Sequence[StreamFrame]) -> QuantizedChunk:
    """Quantize ``frames`` over their union of Gaussians: absent ones get opacity 0 and the rest
    of their record from the nearest frame where they are present (small deltas), then the
    static Gaussians (present everywhere, same record everywhere) go first, each part by id."""
    if not 1 <= len(frames) <= MAX_FRAMES:
        raise ValueError(f"a chunk holds 1..{MAX_FRAMES} frames, got {len(frames)}")
    for k, fr in enumerate(frames):
        _check_frame(k, fr)
    ids = np.unique(np.concatenate([np.asarray(fr.ids, np.int64) for fr in frames]))
    if ids.size > MAX_GAUSSIANS:
        raise ValueError(f"a chunk holds at most {MAX_GAUSSIANS} Gaussians, got {ids.size}")
    dense, present = _dense(frames, ids)
    source = _nearest_present(present)
    dense = {k: np.take_along_axis(v, source[..., None], axis=0) for k, v in dense.items()}
    dense["opacities"][~present] = 0.0
    chunk = _quantized(dense, ids)
    same = np.ones(ids.size, dtype=bool)
    for a in chunk.records.arrays():
        same &= np.all(a == a[:1], axis=(0, 2))
    static = present.all(axis=0) & same
    order = np.concatenate([np.flatnonzero(static), np.flatnonzero(~static)])  # ids are sorted
    chunk.ids, chunk.static = ids[order], int(static.sum())
    chunk.records = chunk.records.select(order)
    return chunk


def pack_chunk(chunk: QuantizedChunk) -> bytes:
    """The gzip bytes of a quantized chunk: header, static block, F delta-coded frame blocks."""
    F, S = chunk.num_frames, chunk.static
    header = HEADER.pack(MAGIC, VERSION, F, chunk.num_gaussians, S, *chunk.position_min.tolist(),
                         *chunk.position_max.tolist(), float(chunk.log_scale_lo), float(chunk.log_scale_hi))
    static = _planes(chunk.records.select(slice(0, S)), 0)
    dynamic = np.stack([_planes(chunk.records.select(slice(S, None)), k) for k in range(F)])
    dynamic[1:] = dynamic[1:] - dynamic[:-1]  # uint8: differences modulo 256, plane by plane
    data = b"".join([header, static.tobytes(), dynamic.tobytes()])
    return gzip.compress(data, GZIP_LEVEL, mtime=0)


def _check_frame(k: int, fr: StreamFrame) -> None:
    n = np.asarray(fr.ids).shape[0]
    shapes = {"ids": (n,), "means": (n, 3), "scales": (n, 3), "quats": (n, 4), "opacities": (n,), "colors": (n, 3)}
    for name, shape in shapes.items():
        a = np.asarray(getattr(fr, name))
        if a.shape != shape:
            raise ValueError(f"frame {k}: {name} has shape {a.shape}, expected {shape}")
        if name != "ids" and not np.isfinite(a).all():
            raise ValueError(f"frame {k}: {name} has non-finite values")
    if np.unique(np.asarray(fr.ids)).size != n:
        raise ValueError(f"frame {k}: the ids are not distinct")


def _dense(frames: Sequence[StreamFrame], ids: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """(F, G, c) float64 arrays of every field over the union ``ids`` (zeros where absent) and
    the (F, G) mask of presence."""
    F, G = len(frames), ids.size
    widths = {"means": 3, "log_scales": 3, "quats": 4, "opacities": 1, "colors": 3}
    dense = {k: np.zeros((F, G, c)) for k, c in widths.items()}
    present = np.zeros((F, G), dtype=bool)
    for k, fr in enumerate(frames):
        at = np.searchsorted(ids, np.asarray(fr.ids, np.int64))
        present[k, at] = True
        dense["means"][k, at] = fr.means
        dense["log_scales"][k, at] = np.log(np.maximum(np.asarray(fr.scales, np.float64), MIN_SCALE))
        dense["quats"][k, at] = fr.quats
        dense["opacities"][k, at, 0] = fr.opacities
        dense["colors"][k, at] = fr.colors
    return dense, present


def _nearest_present(present: np.ndarray) -> np.ndarray:
    """(F, G) the frame each entry takes its values from: itself where present, else the nearest
    frame where the Gaussian is present (the earlier one on a tie)."""
    F, G = present.shape
    before, after = np.empty((F, G), np.int64), np.empty((F, G), np.int64)
    last = np.full(G, -F - 1)  # "no such frame": farther than any real one
    for k in range(F):
        last = np.where(present[k], k, last)
        before[k] = last
    last = np.full(G, 2 * F + 1)
    for k in reversed(range(F)):
        last = np.where(present[k], k, last)
        after[k] = last
    k = np.arange(F)[:, None]
    return np.where(k - before <= after - k, before, after)


def _range(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-column float32 minimum and maximum of (m, c) ``values`` (zeros for m = 0), as the
    header stores them."""
    if values.shape[0] == 0:
        return np.zeros(values.shape[1], np.float32), np.zeros(values.shape[1], np.float32)
    return values.min(axis=0).astype(np.float32), values.max(axis=0).astype(np.float32)


def _steps(values: np.ndarray, lo: np.ndarray, hi: np.ndarray, steps: int) -> np.ndarray:
    """round((v - lo) / (hi - lo) * steps) clamped to 0..steps; 0 where hi == lo (no division)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    span = hi - lo
    t = (values - lo) / np.where(span > 0, span, 1.0)
    return np.clip(np.rint(np.where(span > 0, t, 0.0) * steps), 0, steps)


def _quantized(dense: dict[str, np.ndarray], ids: np.ndarray) -> QuantizedChunk:
    pmin, pmax = _range(dense["means"].reshape(-1, 3))
    lo, hi = (r[0] for r in _range(dense["log_scales"].reshape(-1, 1)))
    q = dense["quats"]
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    unit = np.where(norm > 0, q / np.where(norm > 0, norm, 1.0), np.array([1.0, 0.0, 0.0, 0.0]))
    unit = np.where(unit[..., :1] < 0, -unit, unit)  # q and -q are one rotation: keep w >= 0
    records = Records(
        position=_steps(dense["means"], pmin, pmax, POSITION_STEPS).astype(np.uint16),
        log_scale=_steps(dense["log_scales"], lo, hi, LOG_SCALE_STEPS).astype(np.uint8),
        rotation=np.clip(np.rint(unit * ROTATION_STEPS), -ROTATION_STEPS, ROTATION_STEPS).astype(np.int8),
        opacity=_steps(dense["opacities"], 0.0, 1.0, UNIT_STEPS).astype(np.uint8),
        colour=_steps(dense["colors"], 0.0, 1.0, UNIT_STEPS).astype(np.uint8),
    )
    return QuantizedChunk(ids, 0, records, pmin, pmax, np.float32(lo), np.float32(hi))


def _planes(records: Records, frame: int) -> np.ndarray:
    """(17, n) uint8: frame ``frame``'s block, component-planar, a u16 as its low then high bytes."""
    planes = []
    for f, a in zip(FIELDS, records.arrays()):
        for c in range(f.components):
            column = a[frame, :, c]
            if f.dtype.itemsize == 2:
                planes += [(column & 0xFF).astype(np.uint8), (column >> 8).astype(np.uint8)]
            else:
                planes.append(column.view(np.uint8))
    return np.stack(planes)


# --- reading (the slow reference) ----------------------------------------------------------------


def decode_chunk(data: bytes) -> ChunkFrames:
    """Read a chunk's gzip bytes back into dequantized frames (and their quantized records)."""
    try:
        raw = gzip.decompress(data)
    except (OSError, EOFError, zlib.error) as e:  # BadGzipFile is an OSError
        raise ChunkFormatError(f"not a complete gzip stream ({e})") from None
    if len(raw) < HEADER.size:
        raise ChunkFormatError(f"truncated header: {len(raw)} inflated bytes, a header has {HEADER.size}")
    magic, version, F, G, S, *ranges = HEADER.unpack_from(raw)
    if magic != MAGIC:
        raise ChunkFormatError(f"bad magic {magic!r}: not an ATGS web chunk (expected {MAGIC!r})")
    if version != VERSION:
        raise ChunkFormatError(f"chunk version {version}, this reader reads version {VERSION}")
    if F < 1 or S > G:
        raise ChunkFormatError(f"header says {F} frames, {G} Gaussians, {S} static: needs F >= 1 and S <= G")
    D = G - S
    expected = HEADER.size + RECORD_BYTES * (S + F * D)
    if len(raw) != expected:
        raise ChunkFormatError(f"{len(raw)} inflated bytes where F={F}, G={G}, S={S} need {expected}"
                               f" ({'truncated' if len(raw) < expected else 'trailing bytes'})")
    pmin, pmax = np.array(ranges[0:3], np.float32), np.array(ranges[3:6], np.float32)
    lo, hi = float(np.float32(ranges[6])), float(np.float32(ranges[7]))
    if not (np.isfinite(pmin).all() and np.isfinite(pmax).all() and np.isfinite([lo, hi]).all()):
        raise ChunkFormatError("non-finite position or log-scale range in the header")

    def block(offset: int, n: int) -> np.ndarray:
        return np.frombuffer(raw, np.uint8, RECORD_BYTES * n, offset).reshape(RECORD_BYTES, n)

    static = _from_planes(block(HEADER.size, S))
    offset = HEADER.size + RECORD_BYTES * S
    planes = np.zeros((RECORD_BYTES, D), np.uint8)
    frames = []
    for k in range(F):
        planes = planes + block(offset + k * RECORD_BYTES * D, D)  # uint8: the sum wraps modulo 256
        dynamic = _from_planes(planes)
        records = Records(*(np.concatenate([s, d]) for s, d in zip(static.arrays(), dynamic.arrays())))
        frames.append(_dequantized(records, pmin, pmax, lo, hi))
    return ChunkFrames(G, S, pmin, pmax, lo, hi, frames)


def _from_planes(planes: np.ndarray) -> Records:
    """Inverse of :func:`_planes` for one block: (17, n) uint8 -> records (n, components)."""
    rows = iter(planes)
    arrays = []
    for f in FIELDS:
        columns = []
        for _ in range(f.components):
            if f.dtype.itemsize == 2:
                low, high = next(rows).astype(np.uint16), next(rows).astype(np.uint16)
                columns.append(low | (high << 8))
            else:
                columns.append(next(rows).view(f.dtype))
        arrays.append(np.stack(columns, axis=1).astype(f.dtype))
    return Records(*arrays)


def _dequantized(r: Records, pmin: np.ndarray, pmax: np.ndarray, lo: float, hi: float) -> DecodedFrame:
    p0, p1 = pmin.astype(np.float64), pmax.astype(np.float64)
    means = p0 + r.position / POSITION_STEPS * (p1 - p0)
    log_scales = lo + r.log_scale / LOG_SCALE_STEPS * (hi - lo)
    return DecodedFrame(
        means=means.astype(np.float32),
        scales=np.exp(log_scales).astype(np.float32),
        quats=(r.rotation / ROTATION_STEPS).astype(np.float32),
        opacities=(r.opacity[:, 0] / UNIT_STEPS).astype(np.float32),
        colors=(r.colour / UNIT_STEPS).astype(np.float32),
        records=r,
    )

