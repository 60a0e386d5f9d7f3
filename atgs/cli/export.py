"""``atgs-export CKPT --out DIR``: per-frame 3D Gaussian splatting PLY files of a checkpoint, or
with ``--format web`` a folder a web browser plays (docs/web.md).

Bad input gives one line on stderr and exit code 2 (atgs.io.cli); the output folder appears
complete or not at all (see :mod:`atgs.export`)."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

import tyro

from atgs.io.cli import run_cli
from atgs.web import DEFAULT_PRECISION, DEFAULT_STREAM

if TYPE_CHECKING:
    from atgs.web.export import WebExportResult


@dataclass
class ExportArgs:
    """Export a trained ATGS checkpoint as 3D Gaussian splatting PLY files, one per frame
    (frame_000000.ply, ...), plus manifest.json (fps, frames, cameras); or with --format web as a
    folder a web browser plays (index.html, player/, stream/; serve it with atgs-serve)."""

    ckpt: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="CKPT")]
    """Checkpoint file written by atgs-train (ckpt.pt)."""
    out: Path
    """Output folder; built aside and renamed into place when complete."""
    frames: str | None = None
    """Frames to export: start:stop[:step] (stop exclusive, e.g. 0:120:2) or a list (e.g. 0,30,60); default all."""
    min_opacity: float = 0.0
    """Drop Gaussians whose opacity is below this (e.g. 0.005 keeps files smaller)."""
    format: Literal["ply", "web"] = "ply"
    """ply: one 3DGS PLY file per frame; web: chunked, quantized frames and the browser player (docs/web.md)."""
    web_stream: Literal["model", "gaussians"] = DEFAULT_STREAM  # type: ignore[assignment]
    """With --format web: what the page downloads. model: the model's own tensors, decoded by the
    page on the viewer's GPU (a few times fewer bytes, docs/web.md); gaussians: every frame's
    Gaussians, quantized in chunks."""
    web_precision: Literal["float32", "float16", "int8"] = DEFAULT_PRECISION  # type: ignore[assignment]
    """With --web-stream model: the precision of the anchors and hash grids (the MLPs stay float32)."""
    chunk_frames: int = 8
    """With --web-stream gaussians: frames per chunk file (1..65535); the player downloads a chunk at a time."""
    overwrite: bool = False
    """Replace an existing non-empty output folder (only once the new one is complete)."""
    progress: bool = True
    """Show a progress bar."""


def run(args: ExportArgs):
    from atgs.checkpoint import model_from_checkpoint, read_checkpoint
    from atgs.export import export_ply_sequence, parse_frames
    from atgs.io.atomic import check_output_dir
    from atgs.web.export import check_chunk_frames, export_web

    if args.format == "web" and args.web_stream == "gaussians":
        check_chunk_frames(args.chunk_frames)
    check_output_dir(args.out, args.overwrite)
    ckpt = read_checkpoint(args.ckpt)  # validated; a missing or corrupt file is a one-line error
    model = model_from_checkpoint(ckpt, args.ckpt)
    frames = parse_frames(args.frames, model.num_frames)
    source = {"checkpoint": str(args.ckpt.resolve()), "step": ckpt.get("step")}
    if args.format == "web":
        return export_web(model, args.out, frames, stream=args.web_stream, precision=args.web_precision,
                          chunk_frames=args.chunk_frames, min_opacity=args.min_opacity, overwrite=args.overwrite,
                          source=source, progress=args.progress)
    return export_ply_sequence(model, args.out, frames, min_opacity=args.min_opacity, overwrite=args.overwrite,
                               source=source, progress=args.progress)


def web_summary(res: WebExportResult) -> str:
    """One line: what the web stream costs (its chunk or part files; the player's few files aside)."""
    n, total, gaussian_frames = len(res.frames), res.stream_bytes, sum(res.gaussians)
    if res.stream == "model":
        return (f"atgs-export: wrote the model for {n} frame{'s' if n != 1 else ''} in {len(res.parts)} part files "
                f"to {res.out}: {total:,} bytes, {total / max(n, 1):,.0f} B per frame; serve it with: atgs-serve {res.out}")
    return (f"atgs-export: wrote {n} frame{'s' if n != 1 else ''} ({gaussian_frames / max(n, 1):,.0f} Gaussians per "
            f"frame) in {len(res.chunks)} chunk{'s' if len(res.chunks) != 1 else ''} to {res.out}: {total:,} bytes, "
            f"{total / max(n, 1):,.0f} B per frame, {total / max(gaussian_frames, 1):.2f} B per Gaussian-frame; "
            f"serve it with: atgs-serve {res.out}")


def main(argv: list[str] | None = None) -> int:
    args = tyro.cli(ExportArgs, args=argv, prog="atgs-export")

    def body() -> None:
        res = run(args)
        n = len(res.frames)
        if args.format == "web":
            print(web_summary(res))
            return
        print(f"atgs-export: wrote {n} PLY file{'s' if n != 1 else ''} ({sum(res.gaussians):,} Gaussians) and "
              f"manifest.json to {res.out}")

    return run_cli("atgs-export", body, process=argv is None)


if __name__ == "__main__":
    sys.exit(main())
