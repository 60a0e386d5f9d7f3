"""Atomic outputs: a file or directory appears complete or not at all.

Files are written to a temporary sibling, flushed to disk and renamed into place
(:func:`atomic_file`, :func:`write_bytes_atomic`, :func:`write_text_atomic`,
:func:`write_json_atomic`); an existing file is replaced only by a complete new one.
Directories are built in ``DIR.tmp-xxxx`` and renamed on success (:func:`atomic_dir`, or
:func:`temp_dir_beside` and :func:`publish_dir` for a writer that decides itself what it may
replace); an existing ``DIR`` is never touched on failure, and with ``overwrite=True`` the old
directory is moved aside only after the new one is complete, then deleted. :func:`interprocess_lock`
serializes processes that would build the same cached output (e.g. two ``atgs-train`` runs
started at once on the built-in scene).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from atgs.errors import OutputError


def _fsync_dir(path: Path) -> None:
    """Make a rename in ``path`` durable (best effort: not every file system allows it)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def publish(tmp: str | Path, path: str | Path) -> None:
    """Rename a finished temporary file into place with ordinary permissions (mkstemp makes
    0600 files; a published output gets what the umask gives any new file)."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    os.replace(tmp, path)
    _fsync_dir(Path(path).parent)


@contextlib.contextmanager
def atomic_file(path: str | Path, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path beside ``path`` to write to (``suffix`` keeps an extension that a
    writer needs to pick its format); on normal exit it is fsynced and renamed to ``path``, on an
    exception it is removed and ``path`` stays as it was."""
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"{path}: is a directory; give a file name")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".tmp-", suffix=suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        publish(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_bytes_atomic(path: str | Path, data: bytes) -> None:
    with atomic_file(path) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path: str | Path, text: str) -> None:
    write_bytes_atomic(path, text.encode())


def write_json_atomic(path: str | Path, data: Any, indent: int | None = 1) -> None:
    write_text_atomic(path, json.dumps(data, indent=indent) + "\n")


def check_output_dir(out: Path, overwrite: bool) -> None:
    """Refuse to replace an existing non-empty output unless asked (checked before any work)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: output path exists and is not a directory; choose another --out")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise OutputError(f"{out}: output directory already exists; pass --overwrite to replace it")


def temp_dir_beside(out: Path) -> Path:
    """A new empty directory ``OUT.tmp-xxxx`` beside ``out`` to build it in (same file system:
    :func:`publish_dir` renames it)."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=out.name + ".tmp-", dir=out.parent))


def publish_dir(tmp: Path, out: Path) -> None:
    """Rename the finished directory ``tmp`` to ``out`` with ordinary permissions. An existing
    ``out`` is moved aside first and deleted only once ``tmp`` is in place (put back if the
    rename fails). Whether ``out`` may be replaced is the caller's decision."""
    out = Path(out)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes 0700; a published directory gets what mkdir gives
    old: Path | None = None
    if out.exists():
        old = Path(tempfile.mkdtemp(prefix=out.name + ".old-", dir=out.parent))
        os.rmdir(old)
        os.replace(out, old)
    try:
        os.replace(tmp, out)
    except BaseException:
        if old is not None:
            os.replace(old, out)
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def atomic_dir(out: Path, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary sibling directory; on normal exit it replaces ``out``."""
    out = Path(out)
    check_output_dir(out, overwrite)
    tmp = temp_dir_beside(out)
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if out.exists():
        check_output_dir(out, overwrite)  # something may have appeared while we worked
    publish_dir(tmp, out)


@contextlib.contextmanager
def interprocess_lock(path: Path) -> Iterator[None]:
    """Hold an exclusive lock on the file ``path`` (created if missing) while in the block;
    other processes entering it wait. A no-op where ``fcntl`` does not exist (Windows)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    with open(path, "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def link_or_copy(src: str, dst: str) -> None:
    """Hard-link ``src`` to ``dst`` (a derived scene shares its frames), copying where links fail
    (another filesystem); a ``copy_function`` for shutil.copytree."""
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)
