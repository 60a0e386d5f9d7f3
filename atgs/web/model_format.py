"""The part files of a web export of the model itself (``--web-stream model``; docs/web.md, "A
model part file"): the one owner of their layout in Python.

A part file is a few named tensors of the model (its MLP weights, one keyframe's anchors, one
segment's hash grid) in the precision the export asks for, gzip-compressed:

    "ATGM", u16 version, u16 0, u32 n, n bytes of JSON (space-padded to a multiple of 4), the blobs

The JSON lists each tensor: name, dtype, shape, the byte offset of its blob after the JSON, and
for the quantized dtypes what dequantizes it. Dtypes: ``f32`` (little-endian float32), ``f16``
(float16 as two byte planes: every value's low byte, then every high byte: gzip finds more
repeats in the planes), ``u16`` (positions: ``lo + q / 65535 (hi - lo)`` per column, ``lo``
and ``hi`` in the JSON; byte planes as f16), ``i8`` (``q * scale``; ``scale`` has one row per
equal group of rows, e.g. per hash level, and one column per column). :func:`pack_part` writes
one, :func:`read_part` is the slow plain reference reader the tests hold it to; the browser's
reader is atgs/web/player/model_part.js.
"""

from __future__ import annotations

import gzip
import json
import struct
import zlib
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

MAGIC = b"ATGM"
VERSION = 1
PREAMBLE = struct.Struct("<4sHHI")
GZIP_LEVEL = 9
U16_STEPS = 0xFFFF
I8_STEPS = 127

Precision = Literal["float32", "float16", "int8"]
PRECISIONS: tuple[str, ...] = ("float32", "float16", "int8")


class PartFormatError(ValueError):
    """Bytes that are not a part file this version writes."""


@dataclass
class Encoded:
    """One tensor as stored: dtype, the raw blob and what dequantizes it."""

    name: str
    dtype: str
    shape: tuple[int, ...]
    blob: bytes
    extra: dict = field(default_factory=dict)


def _planes(a: np.ndarray) -> bytes:
    """Two-byte values as byte planes (all low bytes, then all high bytes)."""
    b = np.ascontiguousarray(a).view(np.uint8).reshape(-1, 2)
    return b.T.tobytes()


def _from_planes(blob: bytes, n: int, dtype: str) -> np.ndarray:
    planes = np.frombuffer(blob, np.uint8, 2 * n).reshape(2, n)
    return np.ascontiguousarray(planes.T).view(dtype).reshape(-1)


def encode(name: str, x: np.ndarray, dtype: str, groups: int = 1) -> Encoded:
    """``x`` (rows, columns; a 1D tensor is one column) stored as ``dtype`` (f32, f16, u16, i8).
    ``groups``: i8 scales per equal group of rows (rows must divide)."""
    x = np.asarray(x, np.float32)
    shape = tuple(int(s) for s in x.shape)
    m = x.reshape(shape[0] if x.ndim else 1, -1) if x.ndim != 1 else x.reshape(-1, 1)
    if not np.isfinite(m).all():
        raise ValueError(f"tensor {name!r} has non-finite values")
    if dtype == "f32":
        return Encoded(name, dtype, shape, m.astype("<f4").tobytes())
    if dtype == "f16":
        return Encoded(name, dtype, shape, _planes(m.astype("<f2")))
    if dtype == "u16":
        lo, hi = m.min(0), m.max(0)
        span = np.where(hi > lo, hi - lo, 1.0)
        q = np.rint((m - lo) / span * U16_STEPS).clip(0, U16_STEPS).astype("<u2")
        return Encoded(name, dtype, shape, _planes(q), {"lo": lo.tolist(), "hi": hi.tolist()})
    if dtype == "i8":
        rows = m.shape[0]
        if rows % groups:
            raise ValueError(f"tensor {name!r}: {rows} rows do not split into {groups} groups")
        g = m.reshape(groups, rows // groups, -1)
        scale = np.abs(g).max(1) / I8_STEPS  # (groups, columns)
        scale = np.where(scale > 0, scale, 1.0).astype(np.float32)
        q = np.rint(g / scale[:, None, :]).clip(-I8_STEPS, I8_STEPS).astype(np.int8)
        return Encoded(name, dtype, shape, q.tobytes(), {"scale": scale.tolist()})
    raise ValueError(f"unknown part dtype {dtype!r}")


def pack_part(tensors: list[Encoded]) -> bytes:
    """The gzip bytes of a part file holding ``tensors``."""
    entries, blobs, at = [], [], 0
    for t in tensors:
        entries.append({"name": t.name, "dtype": t.dtype, "shape": list(t.shape), "offset": at, **t.extra})
        pad = -len(t.blob) % 4
        blobs.append(t.blob + b"\0" * pad)
        at += len(t.blob) + pad
    header = json.dumps({"tensors": entries}, separators=(",", ":")).encode()
    header += b" " * (-len(header) % 4)
    raw = PREAMBLE.pack(MAGIC, VERSION, 0, len(header)) + header + b"".join(blobs)
    return gzip.compress(raw, GZIP_LEVEL, mtime=0)


def _decode_tensor(e: dict, data: bytes, where: str) -> np.ndarray:
    shape = tuple(int(s) for s in e["shape"])
    n = int(np.prod(shape)) if shape else 1
    size = {"f32": 4, "f16": 2, "u16": 2, "i8": 1}.get(e["dtype"])
    if size is None:
        raise PartFormatError(f"{where}: tensor {e['name']!r} has unknown dtype {e['dtype']!r}")
    start, end = int(e["offset"]), int(e["offset"]) + size * n
    if end > len(data):
        raise PartFormatError(f"{where}: tensor {e['name']!r} runs past the end (truncated file)")
    blob = data[start:end]
    cols = int(np.prod(shape[1:])) if len(shape) > 1 else 1
    if e["dtype"] == "f32":
        v = np.frombuffer(blob, "<f4").astype(np.float32)
    elif e["dtype"] == "f16":
        v = _from_planes(blob, n, "<f2").astype(np.float32)
    elif e["dtype"] == "u16":
        q = _from_planes(blob, n, "<u2").reshape(-1, cols).astype(np.float64)
        lo, hi = np.asarray(e["lo"], np.float64), np.asarray(e["hi"], np.float64)
        v = (lo + q / U16_STEPS * (hi - lo)).astype(np.float32)
    else:
        scale = np.asarray(e["scale"], np.float32)
        q = np.frombuffer(blob, np.int8).astype(np.float32).reshape(scale.shape[0], -1, cols)
        v = q * scale[:, None, :]
    return v.reshape(shape)


def read_part(data: bytes, where: str = "<part>") -> dict[str, np.ndarray]:
    """A part file's gzip bytes -> its tensors, dequantized to float32 (the reference reader)."""
    try:
        raw = gzip.decompress(data)
    except (OSError, EOFError, zlib.error) as e:
        raise PartFormatError(f"{where}: not a complete gzip stream ({e})") from None
    if len(raw) < PREAMBLE.size:
        raise PartFormatError(f"{where}: truncated ({len(raw)} bytes, the preamble has {PREAMBLE.size})")
    magic, version, _, n = PREAMBLE.unpack_from(raw)
    if magic != MAGIC:
        raise PartFormatError(f"{where}: bad magic {magic!r}, not a model part file (expected {MAGIC!r})")
    if version != VERSION:
        raise PartFormatError(f"{where}: part version {version}, this reader reads version {VERSION}")
    try:
        header = json.loads(raw[PREAMBLE.size:PREAMBLE.size + n])
    except ValueError as e:
        raise PartFormatError(f"{where}: its header is not JSON ({e})") from None
    data_bytes = raw[PREAMBLE.size + n:]
    return {e["name"]: _decode_tensor(e, data_bytes, where) for e in header["tensors"]}
