"""A folder of per-frame 3DGS PLY files: what ``atgs-export`` writes and the player plays.

Layout (the files are :mod:`atgs.io.gaussian_ply`'s format)::

    DIR/
      frame_000000.ply, frame_000002.ply, ...   one file per exported frame, named by its frame
                                                index in the sequence
      manifest.json   {"format": "atgs-ply-sequence", "version": 1, "fps", "num_frames",
                       "frames": [indices], "files": [names], "gaussians": [counts],
                       "sh_degree", "cameras": [Camera.to_dict(), ...], "test_cameras": [names],
                       "min_opacity", "near", "source": {"checkpoint", "step"}}

``near`` is the model's near plane (atgs.model.near_plane): ATGS's players do not draw a Gaussian
at view z <= near, as training did not; a PLY file has no place for it (exports from before it
have none: 0.01).

Folders written by other tools open too: every ``*.ply`` in the folder is a frame, ordered by
the last number in its name (``0001.ply``, ``frame_12.ply``, ``time_00005.ply``); without a
manifest the sequence has no cameras and plays at ``--fps`` (default 30). With one, it plays in
real time: ``fps`` is the sequence's rate, so files exported every s-th frame play at fps / s.
:func:`open_ply_sequence` checks every file's header before anything plays (a truncated file,
a missing property or files whose properties differ are one-line errors naming the file).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from atgs.cameras import Camera
from atgs.io.gaussian_ply import GaussianPlyError, GaussianPlyLayout, read_gaussian_ply_layout
from atgs.render.constants import NEAR

MANIFEST_NAME = "manifest.json"
FORMAT = "atgs-ply-sequence"
VERSION = 1
DEFAULT_FPS = 30.0


def frame_file_name(frame: int) -> str:
    return f"frame_{frame:06d}.ply"


def sequence_manifest(fps: float, num_frames: int, frames: list[int], files: list[str], counts: list[int],
             cameras: list[Camera], test_cameras: list[str], min_opacity: float, source: dict[str, Any],
             sh_degree: int = 0, near: float = NEAR) -> dict[str, Any]:
    """The manifest.json of an exported sequence (see the module docstring)."""
    return {"format": FORMAT, "version": VERSION, "fps": float(fps), "num_frames": int(num_frames),
            "frames": [int(f) for f in frames], "files": list(files), "gaussians": [int(c) for c in counts],
            "sh_degree": int(sh_degree), "cameras": [c.to_dict() for c in cameras],
            "test_cameras": list(test_cameras), "min_opacity": float(min_opacity), "near": float(near),
            "source": source}


@dataclass
class PlySequence:
    """Frames to play: one file (a static scene) or a folder's files in frame-number order."""

    files: list[Path]
    numbers: list[int]  # frame number of each file (its index for a single file: 0)
    fps: float  # files per second when played in real time
    cameras: list[Camera]
    sh_degree: int
    manifest: dict[str, Any] | None = None


def _frame_number(path: Path) -> int | None:
    found = re.findall(r"\d+", path.stem)
    return int(found[-1]) if found else None


def _read_manifest(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise GaussianPlyError(f"{path}: unreadable manifest ({type(e).__name__}: {e}); "
                               "delete it to play the folder without it") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise GaussianPlyError(f"{path}: not an {FORMAT} manifest; delete or rename it to play the folder without it")
    version = data.get("version")
    if not isinstance(version, int) or version < 1:
        raise GaussianPlyError(f"{path}: invalid manifest version {version!r}")
    if version > VERSION:
        raise GaussianPlyError(f"{path}: manifest version {version} is newer than this atgs supports ({VERSION}); "
                               "upgrade atgs")
    fps = data.get("fps")
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not fps > 0:
        raise GaussianPlyError(f"{path}: 'fps' must be a number > 0, got {fps!r}")
    near = data.setdefault("near", NEAR)  # (exports from before the scaled near plane: 0.01)
    if isinstance(near, bool) or not isinstance(near, (int, float)) or not 0 < near < float("inf"):
        raise GaussianPlyError(f"{path}: 'near' must be a number > 0, got {near!r}")
    try:
        data["cameras"] = [Camera.from_dict(c) for c in data.get("cameras") or []]
    except (KeyError, TypeError, ValueError) as e:
        raise GaussianPlyError(f"{path}: bad camera entry ({type(e).__name__}: {e})") from None
    return data


def _check_same_properties(first: GaussianPlyLayout, other: GaussianPlyLayout) -> None:
    a, b = set(first.properties), set(other.properties)
    if a == b:
        return
    only_other, only_first = sorted(b - a), sorted(a - b)
    what = (f"has {', '.join(only_other[:3])}{' ...' if len(only_other) > 3 else ''}" if only_other else
            f"lacks {', '.join(only_first[:3])}{' ...' if len(only_first) > 3 else ''}")
    raise GaussianPlyError(f"{other.path}: {what} unlike {first.path.name} (SH degree {other.sh_degree} vs "
                           f"{first.sh_degree}); the files of a sequence must have the same properties")


def open_ply_sequence(path: str | Path, fps: float | None = None) -> PlySequence:
    """A PLY file or a folder of per-frame PLY files, with every header checked. ``fps``
    overrides the playback rate (default: the manifest's, else 30)."""
    path = Path(path)
    if fps is not None and not fps > 0:
        raise GaussianPlyError(f"--fps {fps}: must be > 0")
    if path.is_file():
        layout = read_gaussian_ply_layout(path)
        return PlySequence([path], [0], fps or DEFAULT_FPS, [], layout.sh_degree)
    if not path.is_dir():
        raise GaussianPlyError(f"{path}: not found; pass a .ply file or a folder of per-frame .ply files")
    files = [p for p in path.iterdir() if p.suffix.lower() == ".ply" and p.is_file()]
    if not files:
        raise GaussianPlyError(f"{path}: no .ply files in the folder; pass a folder of per-frame 3DGS PLY files "
                               "(atgs-export writes one)")
    numbered: dict[int, Path] = {}
    for p in sorted(files):
        n = _frame_number(p)
        if n is None:
            raise GaussianPlyError(f"{p}: no frame number in the file name; name a sequence's files like "
                                   "frame_000000.ply, frame_000001.ply, ... (the number orders them)")
        if n in numbered:
            raise GaussianPlyError(f"{p}: frame number {n} again (also {numbered[n].name}); one file per frame")
        numbered[n] = p
    numbers = sorted(numbered)
    ordered = [numbered[n] for n in numbers]
    layouts = [read_gaussian_ply_layout(p) for p in ordered]
    for other in layouts[1:]:
        _check_same_properties(layouts[0], other)
    man_path = path / MANIFEST_NAME
    man = _read_manifest(man_path) if man_path.is_file() else None
    if fps is None and man is not None:
        span = numbers[-1] - numbers[0]
        # the manifest's rate is the sequence's; every s-th frame exported plays at fps / s
        fps = float(man["fps"]) * ((len(numbers) - 1) / span if span > 0 else 1.0)
    cameras = man["cameras"] if man is not None else []
    return PlySequence(ordered, numbers, fps or DEFAULT_FPS, cameras, layouts[0].sh_degree, man)
