"""Self-describing, validated, atomically written checkpoints (``ckpt.pt``).

A checkpoint is a dict of tensors and plain Python types only, read with
``torch.load(weights_only=True)`` (no pickled code runs)::

    {"format": "atgs-checkpoint", "version": 1,
     "model_config": {...}, "train_config": {...},      # dataclasses as dicts
     "cameras": [Camera.to_dict()], "test_cameras": [names],
     "num_frames": F, "fps": fps, "time_range": [0.0, (F - 1) / fps], "keyframes": [frames],
     "step": int, "model": {...tensors...}, "trainer": {...optimizer state, RNG...} | None,
     "run_id": str}                                     # the run's identity (atgs.train.run_dir)

Tensors are saved on the CPU whatever the device they were trained on, so a checkpoint loads on
any machine; :func:`load_model` / :func:`model_from_checkpoint` move the model to ``device``.
"""

from __future__ import annotations

from pathlib import Path

import torch

from atgs.cameras import Camera
from atgs.device import usable_device
from atgs.errors import UserError
from atgs.io.atomic import atomic_file
from atgs.io.torch_zip import save_streamed
from atgs.render.environment import EnvironmentMap

FORMAT = "atgs-checkpoint"
VERSION = 1
REQUIRED = ("model_config", "cameras", "num_frames", "fps", "model", "step")


class CheckpointError(UserError, ValueError):
    """A file that is not a readable ATGS checkpoint of a supported version."""


def save_checkpoint(path: str | Path, payload: dict) -> None:
    """Write ``payload`` to ``path`` atomically (atgs.io.atomic: temp file, fsync, rename), its
    tensors on the CPU. Tables gathered from several workers may come as
    :class:`~atgs.io.torch_zip.Streamed` tensors: written piece by piece, the same file."""
    with atomic_file(path) as tmp:
        save_streamed({"format": FORMAT, "version": VERSION, **on_cpu(payload)}, tmp)


def on_cpu(tree):
    """``tree`` (dicts, lists, tuples) with every tensor on the CPU (CPU tensors as they are)."""
    if isinstance(tree, torch.Tensor):
        return tree.cpu()
    if isinstance(tree, dict):
        return {k: on_cpu(v) for k, v in tree.items()}
    if isinstance(tree, (list, tuple)):
        return type(tree)(on_cpu(v) for v in tree)
    return tree


def read_checkpoint(path: str | Path, mmap: bool = False) -> dict:
    """Load and validate a checkpoint dict; raises :class:`CheckpointError` with the fix.
    ``mmap``: its tensors map the file (copy on write), so that a reader that keeps a slice of
    a table (a worker of the time partition) reads only that slice's pages."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint not found; pass the ckpt.pt written by atgs-train")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True, mmap=mmap)
    except Exception as e:  # truncated zip, foreign pickle with code, random bytes ...
        raise CheckpointError(f"{path}: not a readable ATGS checkpoint (corrupt, truncated or foreign file: "
                              f"{type(e).__name__}); re-train or pick another file") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not an ATGS checkpoint (format is "
                              f"{data.get('format') if isinstance(data, dict) else type(data).__name__!r}, "
                              f"expected {FORMAT!r})")
    version = data.get("version")
    if not isinstance(version, int) or version < 1:
        raise CheckpointError(f"{path}: invalid checkpoint version {version!r}")
    if version > VERSION:
        raise CheckpointError(f"{path}: checkpoint version {version} is newer than this atgs supports "
                              f"({VERSION}); upgrade atgs")
    missing = [k for k in REQUIRED if k not in data]
    if missing:
        raise CheckpointError(f"{path}: checkpoint is missing {missing}; the file is damaged or foreign")
    return data


def model_from_checkpoint(data: dict, path: str | Path = "<checkpoint>", device: torch.device | str = "cpu",
                          segments: range | None = None):
    """The model of a checkpoint dict (:func:`read_checkpoint`), on ``device``; ``segments``:
    only these time segments' per-segment rows (a worker of the time partition)."""
    from atgs.model.atgs_model import ATGSModel
    from atgs.config_dict import from_dict
    from atgs.model.config import ModelConfig

    try:
        cfg = from_dict(ModelConfig, data["model_config"])
        cameras = [Camera.from_dict(c) for c in data["cameras"]]
        model = ATGSModel.from_state(cfg, data["model"], int(data["num_frames"]), float(data["fps"]), cameras,
                                     segments)
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        raise CheckpointError(f"{path}: checkpoint contents are inconsistent ({type(e).__name__}: {e})") from None
    model.test_camera_names = list(data.get("test_cameras", []))
    bg = (data.get("train_config") or {}).get("background")
    if bg is not None and len(bg) == 3:
        model.background = tuple(float(c) for c in bg)
    env = data.get("environment")
    if env is not None:  # the background by direction (--train.background-by-direction)
        try:
            model.environment = EnvironmentMap.from_state(env)
        except (KeyError, TypeError, ValueError) as e:
            raise CheckpointError(f"{path}: checkpoint's environment map is malformed ({e}); "
                                  "re-save it with atgs-train --resume") from None
    return model.to(usable_device(device))


def load_model(path: str | Path, device: torch.device | str = "cpu"):
    """``atgs.load``: the trained :class:`~atgs.model.atgs_model.ATGSModel` of a checkpoint, on
    ``device`` (checkpoints hold CPU tensors and load on any device)."""
    dev = usable_device(device)  # before reading: a bad device fails fast
    return model_from_checkpoint(read_checkpoint(path), path, dev)
