"""atgs.io: atomic files and videos (complete or not at all), the cache directory, and the CLI
wrapper's exit codes."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import numpy as np
import pytest

from atgs.errors import OutputError, UserError
from atgs.io.atomic import atomic_dir, atomic_file, write_json_atomic
from atgs.io.cache import cache_dir
from atgs.io.cli import Interrupted, run_cli
from atgs.io.video import VideoWriter


def test_atomic_file_replaces_only_when_complete(tmp_path) -> None:
    path = tmp_path / "out.json"
    write_json_atomic(path, {"a": 1})
    before = path.read_bytes()
    with pytest.raises(RuntimeError):
        with atomic_file(path) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed mid-write")
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["out.json"]
    write_json_atomic(path, {"a": 2})
    assert path.read_text() == '{\n "a": 2\n}\n'
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~umask  # not mkstemp's 0600
    with pytest.raises(OutputError, match="is a directory"):
        write_json_atomic(tmp_path, {})


def test_atomic_dir_replaces_only_when_complete(tmp_path) -> None:
    out = tmp_path / "out"
    with atomic_dir(out) as tmp:
        (tmp / "a").write_text("1")
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(out.stat().st_mode) == 0o777 & ~umask  # not mkdtemp's 0700
    with pytest.raises(OutputError, match="--overwrite"):
        with atomic_dir(out):
            pass
    with pytest.raises(RuntimeError):
        with atomic_dir(out, overwrite=True) as tmp:
            (tmp / "b").write_text("half")
            raise RuntimeError("killed mid-write")
    assert [p.name for p in out.iterdir()] == ["a"] and [p.name for p in tmp_path.iterdir()] == ["out"]
    with atomic_dir(out, overwrite=True) as tmp:
        (tmp / "b").write_text("2")
    assert [p.name for p in out.iterdir()] == ["b"] and [p.name for p in tmp_path.iterdir()] == ["out"]


def test_video_writer_publishes_on_close_and_discards_on_error(tmp_path) -> None:
    from atgs.data.video import iter_frames

    frames = [np.full((16, 24, 3), 30 * i, np.uint8) for i in range(3)]
    path = tmp_path / "v.mp4"
    with VideoWriter(path, 24, 16, 10) as w:  # lossless RGB by default
        for f in frames:
            w.write(f)
        assert not path.exists(), "nothing visible before close"
    assert [img for _, img in iter_frames(path)][1].tolist() == frames[1].tolist()
    before = path.read_bytes()
    with pytest.raises(KeyboardInterrupt):
        with VideoWriter(path, 24, 16, 10, codec="libx264", crf=18, pix_fmt="yuv420p") as w:
            w.write(frames[0])
            raise KeyboardInterrupt
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["v.mp4"]
    with pytest.raises(OutputError, match="even width and height"):
        VideoWriter(tmp_path / "odd.mp4", 25, 16, 10, codec="libx264", pix_fmt="yuv420p")
    with pytest.raises(OutputError, match=r"\.mp4"):
        VideoWriter(tmp_path / "v.gif", 24, 16, 10)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.mp4"]


def test_cache_dir_follows_the_environment(monkeypatch, tmp_path) -> None:
    monkeypatch.setenv("ATGS_CACHE_DIR", str(tmp_path / "c"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "x"))
    assert cache_dir() == tmp_path / "c"
    monkeypatch.delenv("ATGS_CACHE_DIR")
    assert cache_dir() == tmp_path / "x" / "atgs"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert cache_dir() == Path.home() / ".cache" / "atgs"
    from atgs.render.build import cache_root

    monkeypatch.setenv("ATGS_CACHE_DIR", str(tmp_path / "c"))
    assert cache_root() == tmp_path / "c" / "torch_extensions"


def test_run_cli_exit_codes(capsys) -> None:
    def fail(exc: BaseException):
        def body() -> None:
            raise exc
        return body

    assert run_cli("cmd", lambda: None) == 0 and run_cli("cmd", lambda: 3) == 3
    assert run_cli("cmd", fail(UserError("x.json: broken\nsecond line"))) == 2
    assert capsys.readouterr().err == "cmd: error: x.json: broken\n"
    assert run_cli("cmd", fail(ValueError("bad --n")), user_errors=(ValueError,)) == 2
    assert capsys.readouterr().err == "cmd: error: bad --n\n"
    assert run_cli("cmd", fail(KeyboardInterrupt())) == 130
    assert capsys.readouterr().err == "cmd: interrupted\n"
    assert run_cli("cmd", fail(Interrupted("checkpoint saved"))) == 130
    assert capsys.readouterr().err == "cmd: interrupted: checkpoint saved\n"
    with pytest.raises(ValueError):  # a programming error keeps its traceback
        run_cli("cmd", fail(ValueError("bug")))


def test_frame_dir_writer_publishes_whole_renders_through_atomic(tmp_path) -> None:
    """PNG frames appear at close only, with a directory's ordinary permissions, replacing an
    earlier render whole (no stray frames, no temporary siblings left); abort leaves nothing."""
    from atgs.viewer.errors import ViewerError
    from atgs.viewer.output import FrameDirWriter

    out = tmp_path / "frames"
    with FrameDirWriter(out) as w:
        for i in range(3):
            w.write(np.full((4, 6, 3), 40 * i, np.uint8))
        assert not out.exists(), "nothing visible before close"
    assert sorted(p.name for p in out.iterdir()) == ["00000.png", "00001.png", "00002.png"]
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(out.stat().st_mode) == 0o777 & ~umask
    with FrameDirWriter(out) as w:
        w.write(np.zeros((4, 6, 3), np.uint8))
    assert [p.name for p in out.iterdir()] == ["00000.png"] and [p.name for p in tmp_path.iterdir()] == ["frames"]
    with pytest.raises(KeyboardInterrupt):
        with FrameDirWriter(out) as w:
            w.write(np.full((4, 6, 3), 255, np.uint8))
            raise KeyboardInterrupt
    assert [p.name for p in tmp_path.iterdir()] == ["frames"]
    (out / "notes.txt").write_text("mine")
    with pytest.raises(ViewerError, match="other files than rendered frames"):
        FrameDirWriter(out)
