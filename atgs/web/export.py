"""A trained model -> a folder a web browser plays (``atgs-export --format web``, docs/web.md).

Two kinds of stream, one strategy object each (:data:`STREAM_KINDS`), chosen by ``stream``:

- ``gaussians``: frames are decoded with stable Gaussian ids (the training decode names each
  Gaussian by its anchor and slot), grouped into chunks of ``chunk_frames``
  (:mod:`atgs.web.stream_format`);
- ``model``: the model's own tensors in part files, decoded by the page on the viewer's GPU
  (:mod:`atgs.web.model_stream`).

Either is written with manifest.json, the environment map if any, and the player page copied
from atgs/web/player.
The folder is built aside and renamed into place (:func:`atgs.io.atomic.atomic_dir`), so a failed
export leaves nothing and an existing folder is replaced only with ``overwrite``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib.resources import files
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from atgs.errors import OutputError
from atgs.export import ExportError
from atgs.io.atomic import atomic_dir, check_output_dir, write_json_atomic
from atgs.progress import progress_bar
from atgs.threads import torch_threads
from atgs.web import DEFAULT_PRECISION, DEFAULT_STREAM
from atgs.web.manifest import (ENVIRONMENT_NAME, MANIFEST_NAME, ChunkInfo, chunk_entries, chunk_file_name,
                               stream_entries)
from atgs.web.model_format import PRECISIONS
from atgs.web.model_stream import KIND as MODEL_KIND
from atgs.web.model_stream import ModelStreamUnavailable, PartInfo, write_model_stream
from atgs.web.stream_format import MAX_FRAMES, StreamFrame, pack_chunk, quantize_chunk

STREAM_DIR = "stream"
PLAYER_DIR = "player"
PAGE_NAME = "index.html"




@dataclass
class WebExportResult:
    out: Path
    frames: list[int]
    gaussians: list[int]  # Gaussians present in each exported frame (empty for a model stream)
    chunks: list[ChunkInfo]  # the chunk files (a Gaussian stream)
    parts: list[PartInfo] = field(default_factory=list)  # the part files (a model stream)
    stream: str = "gaussians"

    @property
    def stream_bytes(self) -> int:
        """The stream's files' total size: what playing the whole video downloads."""
        return sum(c.bytes for c in self.chunks) + sum(p.bytes for p in self.parts)


def check_chunk_frames(chunk_frames: int) -> None:
    if not 1 <= chunk_frames <= MAX_FRAMES:
        raise ExportError(f"--chunk-frames {chunk_frames}: must be within 1..{MAX_FRAMES} (a chunk's frame count is a u16)")


def export_web(model, out: str | Path, frames: list[int], *, stream: str = DEFAULT_STREAM,
               precision: str = DEFAULT_PRECISION, chunk_frames: int = 8, min_opacity: float = 0.0,
               overwrite: bool = False, source: dict[str, Any] | None = None, progress: bool = True) -> WebExportResult:
    """Write ``frames`` of ``model`` as the web folder ``out`` (docs/web.md) as a stream of kind
    ``stream`` (:data:`STREAM_KINDS`). Gaussians: ``chunk_frames`` a chunk, dropping Gaussians
    whose opacity is below ``min_opacity`` from the frames where it is; model: the big tensors at
    ``precision``."""
    out = Path(out)
    kind = STREAM_KINDS.get(stream)
    if kind is None:
        raise ExportError(f"--web-stream {stream}: must be one of {', '.join(STREAM_KINDS)}")
    kind.check(model, chunk_frames=chunk_frames, min_opacity=min_opacity, precision=precision)
    check_output_dir(out, overwrite)  # before decoding anything
    try:
        with atomic_dir(out, overwrite) as tmp:
            (tmp / STREAM_DIR).mkdir()
            res, entries = kind.write(model, tmp / STREAM_DIR, frames, chunk_frames=chunk_frames,
                                      min_opacity=min_opacity, precision=precision, progress=progress)
            write_environment(model, tmp / STREAM_DIR)
            write_json_atomic(tmp / STREAM_DIR / MANIFEST_NAME, {**stream_entries(model, frames, source or {}), **entries})
            copy_player(tmp)
    except OSError as e:  # a full disk, no permission: the folder being built was removed
        raise OutputError(f"{out}: cannot write the export ({e.strerror or e}); nothing was written") from None
    res.out = out
    return res


class GaussianStream:
    """Every frame's Gaussians, quantized in chunks (:mod:`atgs.web.stream_format`)."""

    @staticmethod
    def check(model, *, chunk_frames: int, min_opacity: float, **_) -> None:
        check_chunk_frames(chunk_frames)
        if not 0.0 <= min_opacity < 1.0:
            raise ExportError(f"--min-opacity {min_opacity}: must be in [0, 1)")

    @staticmethod
    def write(model, folder: Path, frames: list[int], *, chunk_frames: int, min_opacity: float, progress: bool,
              **_) -> tuple[WebExportResult, dict]:
        counts, chunks = _write_stream(model, folder, frames, chunk_frames, min_opacity, progress)
        return WebExportResult(folder, list(frames), counts, chunks), chunk_entries(chunk_frames, chunks)


class ModelStream:
    """The model's tensors; the page decodes them (:mod:`atgs.web.model_stream`)."""

    @staticmethod
    def check(model, *, precision: str, min_opacity: float, **_) -> None:
        if precision not in PRECISIONS:
            raise ExportError(f"--web-precision {precision}: must be one of {', '.join(PRECISIONS)}")
        if min_opacity > 0:
            raise ExportError("--min-opacity applies to --web-stream gaussians only (the model stream "
                              "drops what the model's own opacity cut drops)")
        try:
            from atgs.web.model_stream import check_streamable

            check_streamable(model)
        except ModelStreamUnavailable as e:
            raise ExportError(f"{e}; use --web-stream gaussians") from None

    @staticmethod
    def write(model, folder: Path, frames: list[int], *, precision: str, **_) -> tuple[WebExportResult, dict]:
        with torch_threads(1):
            entry, parts = write_model_stream(model, folder, frames, precision)
        return WebExportResult(folder, list(frames), [], [], parts, MODEL_KIND), {"kind": MODEL_KIND, "model": entry}


STREAM_KINDS = {"model": ModelStream, "gaussians": GaussianStream}


def frame_with_ids(model, f: int, min_opacity: float = 0.0) -> StreamFrame:
    """Frame ``f`` by the training decode (no autograd), each Gaussian named by its model id
    ``anchor * gaussians_per_anchor + slot`` (the same Gaussian keeps its id across frames)."""
    with torch.no_grad():
        d = model.decode_frame(f, None, track=False)
    g = d.gaussians
    ids = d.anchor_ids * model.cfg.gaussians_per_anchor + d.slot_ids
    keep = g.opacities >= min_opacity
    arrays = [x[keep].detach().cpu().numpy() for x in (ids, g.means, g.scales, g.quats, g.opacities, g.colors)]
    return StreamFrame(*arrays)


def _write_stream(model, folder: Path, frames: list[int], chunk_frames: int, min_opacity: float,
                  progress: bool) -> tuple[list[int], list[ChunkInfo]]:
    counts: list[int] = []
    chunks: list[ChunkInfo] = []
    # one torch thread: 20-25x faster decodes than two under load on 2 cores (atgs.threads)
    with progress_bar(len(frames), "atgs-export", unit="frame", enabled=progress) as bar, torch_threads(1):
        for start in range(0, len(frames), chunk_frames):
            decoded = []
            for f in frames[start:start + chunk_frames]:
                decoded.append(frame_with_ids(model, f, min_opacity))
                counts.append(len(decoded[-1].ids))
                bar.update(1)
            quantized = quantize_chunk(decoded)
            name = chunk_file_name(len(chunks))
            data = pack_chunk(quantized)
            (folder / name).write_bytes(data)
            chunks.append(ChunkInfo(name, len(decoded), quantized.num_gaussians, quantized.static, len(data)))
    return counts, chunks


def write_environment(model, folder: Path) -> None:
    """stream/environment.png: the model's background by direction, if it has one."""
    env = getattr(model, "environment", None)
    if env is not None:  # its texels are linear colours in [0, 1]: stored as they are, 8 bits
        texels = env.texels.clamp(0, 1).mul(255).round().to(torch.uint8).numpy()
        Image.fromarray(np.ascontiguousarray(texels), "RGB").save(folder / ENVIRONMENT_NAME)


def copy_player(out: Path) -> list[str]:
    """Copy the player shipped in atgs/web/player (whatever *.js, *.css and index.html it holds)
    into ``out``: index.html at the top, the rest under player/. Returns the names copied."""
    source = files("atgs.web") / PLAYER_DIR
    copied = []
    if not source.is_dir():
        return copied
    (out / PLAYER_DIR).mkdir(exist_ok=True)
    for item in sorted(source.iterdir(), key=lambda p: p.name):
        if item.name == PAGE_NAME:
            (out / PAGE_NAME).write_bytes(item.read_bytes())
        elif item.is_file() and item.name.endswith((".js", ".css")):
            (out / PLAYER_DIR / item.name).write_bytes(item.read_bytes())
        else:
            continue
        copied.append(item.name)
    return copied
