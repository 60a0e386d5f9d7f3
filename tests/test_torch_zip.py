"""atgs.io.torch_zip: a file with Streamed tensors is the file torch.save writes of the whole.

References: torch.save of the same object with every Streamed materialized (what the trainer
wrote before), torch.load, and Python's zipfile, which checks every record's CRC-32."""

from __future__ import annotations

import collections
import zipfile

import pytest
import torch

from atgs.checkpoint import read_checkpoint, save_checkpoint
from atgs.io.torch_zip import Streamed, save_streamed


def _split(t: torch.Tensor, cuts: list[int]):
    """``t``'s rows as pieces cut at ``cuts`` (empty pieces included)."""
    edges = [0, *cuts, t.shape[0]]
    return lambda: (t[a:b] for a, b in zip(edges, edges[1:]))


def _materialized(obj):
    if isinstance(obj, Streamed):
        return torch.cat(list(obj.pieces()))
    if isinstance(obj, dict):
        return type(obj)((k, _materialized(v)) for k, v in obj.items())
    if isinstance(obj, (list, tuple)):
        return type(obj)(_materialized(v) for v in obj)
    return obj


def _assert_same(a, b):
    assert type(a) is type(b)
    if isinstance(a, torch.Tensor):
        assert a.dtype == b.dtype and a.shape == b.shape and torch.equal(a, b)
    elif isinstance(a, dict):
        assert list(a) == list(b)
        for k in a:
            _assert_same(a[k], b[k])
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b)
        for x, y in zip(a, b):
            _assert_same(x, y)
    else:
        assert a == b


def _case():
    g = torch.Generator().manual_seed(0)
    table = torch.randn(1000, 7, generator=g)
    flags = torch.rand(300, 2, generator=g) > 0.5
    ints = torch.randint(-5, 5, (50,), generator=g)
    shared = torch.arange(12.0)
    return {
        "format": "x", "step": 3, "shared": shared, "again": shared, "view": table[5:9, 2],
        "model": collections.OrderedDict(table=Streamed((1000, 7), torch.float32, _split(table, [300, 300, 999]), 2),
                                         half=torch.ones(4, dtype=torch.float16)),
        "flags": Streamed((300, 2), torch.bool, _split(flags, [1]), 0),
        "nested": [1, 2.5, (torch.tensor(3), "z"), Streamed((50,), torch.int64, _split(ints, [10, 20]), 1)],
        "empty": torch.zeros(0, 3), "empty_streamed": Streamed((0, 3), torch.float32, _split(torch.zeros(0, 3), [])),
    }


def test_a_streamed_file_loads_as_torch_save_of_the_whole_and_its_crcs_hold(tmp_path):
    obj = _case()
    save_streamed(obj, tmp_path / "streamed.pt")
    torch.save(_materialized(obj), tmp_path / "reference.pt")
    with zipfile.ZipFile(tmp_path / "streamed.pt") as zf:
        assert zf.testzip() is None  # every record's CRC-32, the streamed ones' included
        crcs = {i.filename.split("/", 1)[1]: i.CRC for i in zf.infolist() if "/data/" in i.filename}
    with zipfile.ZipFile(tmp_path / "reference.pt") as zf:
        assert crcs == {i.filename.split("/", 1)[1]: i.CRC for i in zf.infolist() if "/data/" in i.filename}
    got = torch.load(tmp_path / "streamed.pt", weights_only=True)
    _assert_same(got, torch.load(tmp_path / "reference.pt", weights_only=True))
    assert got["again"] is got["shared"]  # one storage stays one
    _assert_same(torch.load(tmp_path / "streamed.pt", weights_only=True, mmap=True), got)


def test_streamed_tensors_are_written_one_after_the_other_in_their_sequence(tmp_path):
    calls = []

    def pieces(name, n):
        def gen():
            calls.append(f"{name} starts")
            for i in range(n):
                calls.append(f"{name} piece {i}")
                yield torch.full((1,), float(i))
            calls.append(f"{name} ends")
        return gen

    obj = {"b": Streamed((2,), torch.float32, pieces("b", 2), 1), "a": Streamed((1,), torch.float32, pieces("a", 1), 0),
           "c": [Streamed((3,), torch.float32, pieces("c", 3), 2)]}
    save_streamed(obj, tmp_path / "f.pt")
    assert calls == ["a starts", "a piece 0", "a ends", "b starts", "b piece 0", "b piece 1", "b ends",
                     "c starts", "c piece 0", "c piece 1", "c piece 2", "c ends"]
    assert torch.load(tmp_path / "f.pt", weights_only=True)["c"][0].tolist() == [0.0, 1.0, 2.0]


def test_pieces_that_do_not_add_up_fail_and_leave_the_old_checkpoint(tmp_path):
    path = tmp_path / "ckpt.pt"
    good = {"model_config": {}, "cameras": [], "num_frames": 1, "fps": 1.0, "step": 1,
            "model": {"t": Streamed((4,), torch.float32, lambda: iter([torch.ones(4)]))}}
    save_checkpoint(path, good)
    assert read_checkpoint(path)["model"]["t"].tolist() == [1.0] * 4
    short = {**good, "step": 2, "model": {"t": Streamed((4,), torch.float32, lambda: iter([torch.ones(3)]))}}
    with pytest.raises(ValueError, match="received 12"):
        save_checkpoint(path, short)
    assert read_checkpoint(path)["step"] == 1
    assert [p.name for p in tmp_path.iterdir()] == ["ckpt.pt"]  # no temporary left behind


@pytest.mark.parametrize("streamed", [False, True])
def test_read_rows_gives_the_rows_a_full_load_gives(tmp_path, streamed):
    from atgs.io.torch_zip import read_rows

    obj = _case()
    g = torch.Generator().manual_seed(1)
    base = torch.randn(40, 3, generator=g)
    obj["offset_view"] = base[10:30]  # a tensor at an offset into its storage
    obj["ints"] = torch.arange(24, dtype=torch.int64).reshape(12, 2)
    if streamed:
        save_streamed(obj, tmp_path / "f.pt")
    else:
        torch.save(_materialized(obj), tmp_path / "f.pt")
    full = torch.load(tmp_path / "f.pt", weights_only=True)
    wanted = {("model", "table"): range(250, 731), ("offset_view",): range(3, 9), ("flags",): range(0, 300),
              ("ints",): range(12, 12), ("nested", 3): range(49, 50)}
    data = torch.load(tmp_path / "f.pt", weights_only=True, mmap=True)
    read_rows(tmp_path / "f.pt", data, wanted)
    for keys, rows in wanted.items():
        got, ref = data, full
        for k in keys:
            got, ref = got[k], ref[k]
        assert got.dtype == ref.dtype and torch.equal(got, ref[rows.start:rows.stop]), keys
    assert torch.equal(data["shared"], full["shared"])  # the rest as loaded
    with pytest.raises(ValueError, match="cannot give rows"):
        read_rows(tmp_path / "f.pt", torch.load(tmp_path / "f.pt", weights_only=True, mmap=True),
                  {("ints",): range(5, 13)})


def test_read_rows_runs_no_global_but_tensors_storages_and_ordered_dicts(tmp_path):
    """The record map reads the pickle itself: a global a checkpoint never holds is refused, not
    called (torch.load(weights_only=True) refuses it too)."""
    import pickle

    from atgs.io.torch_zip import read_rows

    torch.save({"t": torch.arange(6.0).reshape(3, 2), "odd": collections.Counter(a=1)}, tmp_path / "f.pt")
    data = torch.load(tmp_path / "f.pt", weights_only=False, mmap=True)
    with pytest.raises(pickle.UnpicklingError, match="collections.Counter"):
        read_rows(tmp_path / "f.pt", data, {("t",): range(1, 2)})
