"""``torch.save`` files some of whose tensors are written piece by piece as they arrive, and
reading some tensors' rows out of such a file without reading the rest.

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
order of pickling. :func:`read_rows` uses the same map of records to read a slice of rows of a
tensor of a memory-mapped checkpoint with ordinary reads (a worker resuming its share).
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
        if (module, name) == ("collections", "OrderedDict") or (module == "torch" and name.endswith("Storage")):
            return super().find_class(module, name)
        # (a checkpoint of plain values and tensors has no other global: nothing else is run)
        raise pickle.UnpicklingError(f"unexpected global {module}.{name} in a checkpoint")


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
    if not streamed:  # nothing to stream: torch's own writer
        torch.save(obj, path)
        return
    with torch.serialization.skip_data():
        torch.save(laid_out, path)
    reader, slots = _records(path)
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


def _records(path: Path):
    """The file's reader and its pickle's tree with every tensor as its :class:`_Slot`."""
    reader = torch._C.PyTorchFileReader(str(path))
    return reader, _RecordKeys(io.BytesIO(reader.get_record("data.pkl"))).load()


def read_rows(path: str | Path, data: dict, wanted: dict[tuple[str, ...], range]) -> None:
    """Replace, in ``data`` (``torch.load(path, mmap=True)`` of the same file), each tensor at a
    key path of ``wanted`` by a new tensor of only those rows (of its first dimension), read
    from the file with ordinary reads: the map's pages of the tensor are never touched, so the
    reader's resident memory holds the rows it keeps and nothing of the rest."""
    path = Path(path)
    reader, slots = _records(path)
    with open(path, "rb") as fh:
        for keys, rows in wanted.items():
            t, slot = data, slots
            for k in keys[:-1]:
                t, slot = t[k], slot[k]
            whole, slot = t[keys[-1]], slot[keys[-1]]
            if not whole.is_contiguous() or not 0 <= rows.start <= rows.stop <= whole.shape[0]:
                raise ValueError(f"{path}: {'/'.join(keys)} cannot give rows {rows.start}..{rows.stop}")
            out = torch.empty((len(rows), *whole.shape[1:]), dtype=whole.dtype, device="cpu")
            row = out[0:1].numel() * out.element_size() if len(rows) else 0
            fh.seek(reader.get_record_offset(f"data/{slot.key}") + slot.offset * whole.element_size()
                    + rows.start * row)
            if len(rows) and fh.readinto(out.reshape(-1).view(torch.uint8).numpy()) != out.numel() * out.element_size():
                raise ValueError(f"{path}: {'/'.join(keys)} is truncated; the file is damaged")
            t[keys[-1]] = out


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
