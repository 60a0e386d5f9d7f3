"""A trained model -> a folder a web browser plays (``atgs-export --format web``, docs/web.md).

Frames are decoded with stable Gaussian ids (the training decode names each Gaussian by its anchor
and slot), grouped into chunks of ``chunk_frames`` (:mod:`atgs.web.stream_format`) and written
with manifest.json, the environment map if any, and the player page copied from atgs/web/player.
The folder is built aside and renamed into place (:func:`atgs.io.atomic.atomic_dir`), so a failed
export leaves nothing and an existing folder is replaced only with ``overwrite``.
"""

from __future__ import annotations

from dataclasses import dataclass
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
from atgs.web.manifest import ENVIRONMENT_NAME, MANIFEST_NAME, ChunkInfo, chunk_file_name, web_manifest
from atgs.web.stream_format import MAX_FRAMES, StreamFrame, pack_chunk, quantize_chunk

STREAM_DIR = "stream"
PLAYER_DIR = "player"
PAGE_NAME = "index.html"


@dataclass
class WebExportResult:
    out: Path
    frames: list[int]
    gaussians: list[int]  # Gaussians present in each exported frame
    chunks: list[ChunkInfo]

    @property
    def stream_bytes(self) -> int:
        """The chunk files' total size: what playing the whole video downloads."""
        return sum(c.bytes for c in self.chunks)


def check_chunk_frames(chunk_frames: int) -> None:
    if not 1 <= chunk_frames <= MAX_FRAMES:
        raise ExportError(f"--chunk-frames {chunk_frames}: must be within 1..{MAX_FRAMES} (a chunk's frame count is a u16)")


def export_web(model, out: str | Path, frames: list[int], *, chunk_frames: int = 8, min_opacity: float = 0.0,
               overwrite: bool = False, source: dict[str, Any] | None = None, progress: bool = True) -> WebExportResult:
    """Write ``frames`` of ``model`` as the web folder ``out`` (docs/web.md), dropping Gaussians
    whose opacity is below ``min_opacity`` from the frames where it is."""
    out = Path(out)
    check_chunk_frames(chunk_frames)
    if not 0.0 <= min_opacity < 1.0:
        raise ExportError(f"--min-opacity {min_opacity}: must be in [0, 1)")
    check_output_dir(out, overwrite)  # before decoding anything
    try:
        with atomic_dir(out, overwrite) as tmp:
            counts, chunks = _write_stream(model, tmp / STREAM_DIR, frames, chunk_frames, min_opacity, progress)
            write_json_atomic(tmp / STREAM_DIR / MANIFEST_NAME,
                              web_manifest(model, frames, chunk_frames, chunks, source or {}))
            copy_player(tmp)
    except OSError as e:  # a full disk, no permission: the folder being built was removed
        raise OutputError(f"{out}: cannot write the export ({e.strerror or e}); nothing was written") from None
    return WebExportResult(out, list(frames), counts, chunks)


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
    folder.mkdir()
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
    env = getattr(model, "environment", None)
    if env is not None:  # its texels are linear colours in [0, 1]: stored as they are, 8 bits
        texels = env.texels.clamp(0, 1).mul(255).round().to(torch.uint8).numpy()
        Image.fromarray(np.ascontiguousarray(texels), "RGB").save(folder / ENVIRONMENT_NAME)
    return counts, chunks


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
