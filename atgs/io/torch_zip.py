"""``torch.save`` files some of whose tensors are written piece by piece as they arrive.

A writer that gathers a large table from several processes (the time-partitioned trainer's
checkpoint) would otherwise hold the whole table once before ``torch.save`` could write it.
:func:`save_streamed` writes the same file ``torch.save`` writes, ``torch.load`` reads it as
usual, but a :class:`Streamed` tensor's bytes go to disk one piece at a time: the writer holds
one piece, never the whole.

How: ``torch.save`` under ``torch.serialization.skip_data`` lays out the archive (the pickle,
every record's header and reserved space) without writing any tensor bytes; then every record's
bytes are written at its offset in the file (``PyTorchFileReader.get_record_offset``) and the
records' CRC-32s, left 0 by ``skip_data``, are set in their data descriptors and the central
directory, so the file is a valid zip archive (``zipfile.testzip`` passes) as torch's own is.
Which record holds which tensor is read back from the written pickle, not assumed from the
order of pickling.
"""

from __future__ import annotations

import io
import pickle
import zipfile
import zlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import torch


@dataclass(frozen=True)
class Streamed:
    """A tensor of ``shape`` and ``dtype`` (C-contiguous) whose bytes ``pieces()`` yields as
    tensors in row order (their bytes must add up to the whole). The file's Streamed tensors are
    written, and their ``pieces`` called, one after the other in ascending ``sequence``: a
    producer whose pieces come from collectives relies on that order."""

    shape: tuple[int, ...]
    dtype: torch.dtype
    pieces: Callable[[], Iterable[torch.Tensor]]
    sequence: int = 0

    @property
    def nbytes(self) -> int:
        n = torch.empty((), dtype=self.dtype).element_size()
        for s in self.shape:
            n *= s
        return n


class _Slot:
    """Where the pickle put one tensor: its record's key and element offset."""

    def __init__(self, key: str, offset: int) -> None:
        self.key, self.offset = key, offset


class _RecordKeys(pickle.Unpickler):
    """Reads a ``data.pkl`` into the same tree with every tensor replaced by its :class:`_Slot`."""

    def persistent_load(self, pid):  # ("storage", storage type, key, location, numel)
        return pid[2]

    def find_class(self, module, name):
        if (module, name) == ("torch._utils", "_rebuild_tensor_v2"):
            return lambda key, offset, *rest: _Slot(key, offset)
        return super().find_class(module, name)


def _pairs(obj, slots, out: list) -> None:
    """Every (tensor or Streamed of ``obj``, its slot of the parallel tree ``slots``)."""
    if isinstance(obj, (torch.Tensor, Streamed)):
        out.append((obj, slots))
    elif isinstance(obj, dict):
        for k, v in obj.items():
            _pairs(v, slots[k], out)
    elif isinstance(obj, (list, tuple)):
        for v, s in zip(obj, slots, strict=True):
            _pairs(v, s, out)


def _placeholders(obj, streamed: dict[int, Streamed]):
    """``obj`` with each Streamed replaced by an empty tensor of its shape (never written to, so
    its pages are never touched); ``streamed``: placeholder id -> Streamed."""
    if isinstance(obj, Streamed):
        t = torch.empty(obj.shape, dtype=obj.dtype, device="cpu")
        streamed[id(t)] = obj
        return t
    if isinstance(obj, dict):
        return type(obj)((k, _placeholders(v, streamed)) for k, v in obj.items())
    if isinstance(obj, (list, tuple)):
        return type(obj)(_placeholders(v, streamed) for v in obj)
    return obj


def has_streamed(obj) -> bool:
    if isinstance(obj, Streamed):
        return True
    if isinstance(obj, dict):
        return any(has_streamed(v) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return any(has_streamed(v) for v in obj)
    return False


def _bytes_of(storage: torch.UntypedStorage):
    """A buffer over ``storage``'s bytes (no copy)."""
    return torch.empty(0, dtype=torch.uint8).set_(storage).numpy()


def _piece_bytes(t: torch.Tensor):
    t = t.detach().cpu().contiguous()
    return t.reshape(-1).view(torch.uint8).numpy() if t.numel() else b""


def save_streamed(obj, path: str | Path) -> None:
    """``torch.save(obj, path)`` with every :class:`Streamed` in ``obj`` (dicts, lists and tuples
    of tensors and plain values) written piece by piece. CPU tensors only."""
    path = Path(path)
    streamed: dict[int, Streamed] = {}
    laid_out = _placeholders(obj, streamed)
    with torch.serialization.skip_data():
        torch.save(laid_out, path)
    reader = torch._C.PyTorchFileReader(str(path))
    slots = _RecordKeys(io.BytesIO(reader.get_record("data.pkl"))).load()
    pairs: list = []
    _pairs(laid_out, slots, pairs)
    stored: dict[str, torch.UntypedStorage] = {}
    late: list[tuple[str, Streamed]] = []
    for t, slot in pairs:
        if id(t) in streamed:
            if slot.offset != 0:
                raise AssertionError("a streamed tensor must be its record's only tensor")
            late.append((slot.key, streamed.pop(id(t))))
        else:
            stored.setdefault(slot.key, t.untyped_storage())
    crcs: dict[str, int] = {}
    with open(path, "r+b") as fh:
        for key, storage in stored.items():
            fh.seek(reader.get_record_offset(f"data/{key}"))
            data = _bytes_of(storage)
            fh.write(data)
            crcs[key] = zlib.crc32(data)
        for key, s in sorted(late, key=lambda ks: ks[1].sequence):  # (stable: equal ones in tree order)
            fh.seek(reader.get_record_offset(f"data/{key}"))
            crc = written = 0
            for piece in s.pieces():
                data = _piece_bytes(piece)
                fh.write(data)
                crc = zlib.crc32(data, crc)
                written += len(data)
            if written != s.nbytes:
                raise ValueError(f"{path}: a streamed tensor of {s.nbytes} bytes received {written}")
            crcs[key] = crc
        _set_crcs(fh, path, crcs)


def _set_crcs(fh, path: Path, crcs: dict[str, int]) -> None:
    """Write each record's CRC-32 where ``skip_data`` left 0: its data descriptor (torch's writer
    puts one after every non-empty record) or local header, and its central-directory entry."""
    with zipfile.ZipFile(path) as zf:
        infos = {i.filename.split("/", 1)[1]: i for i in zf.infolist()}
        start = zf.start_dir
    for key, crc in crcs.items():
        info = infos[f"data/{key}"]
        if not info.flag_bits & 0x08:  # no data descriptor (an empty record): the local header holds it
            fh.seek(info.header_offset + 14)
            fh.write(crc.to_bytes(4, "little"))
            continue
        fh.seek(info.header_offset)
        head = fh.read(30)
        name_len, extra_len = int.from_bytes(head[26:28], "little"), int.from_bytes(head[28:30], "little")
        fh.seek(info.header_offset + 30 + name_len + extra_len + info.file_size)
        if fh.read(4) != b"PK\x07\x08":
            raise AssertionError(f"{path}: record data/{key} has no data descriptor where its flags say")
        fh.write(crc.to_bytes(4, "little"))
    fh.seek(start)
    central = fh.read()
    at = 0
    while central[at:at + 4] == b"PK\x01\x02":
        n, m, k = (int.from_bytes(central[at + o:at + o + 2], "little") for o in (28, 30, 32))
        name = central[at + 46:at + 46 + n].decode().split("/", 1)[1]
        if name.startswith("data/") and name[5:] in crcs:
            fh.seek(start + at + 16)
            fh.write(crcs[name[5:]].to_bytes(4, "little"))
        at += 46 + n + m + k
