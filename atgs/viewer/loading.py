"""Open what the viewer plays: a checkpoint (through the model API), 3DGS PLY files (one file
or a folder of per-frame files, viewer.ply_source) or the built-in demo scene."""

from __future__ import annotations

from pathlib import Path

from atgs.viewer.errors import ViewerError
from atgs.viewer.source import GaussianSource, SyntheticSource

DEMO = "demo"  # `atgs-view demo` plays the built-in synthetic scene (no checkpoint needed)


def is_ply_input(path: str | Path) -> bool:
    """A .ply file or a folder (of per-frame .ply files), rather than a checkpoint."""
    p = Path(path)
    return p.suffix.lower() == ".ply" or p.is_dir()


def load_source(path: str | Path, demo_gaussians: int = 20000, fps: float | None = None) -> GaussianSource:
    """A checkpoint path -> the loaded model (``atgs.load``: a bad file raises CheckpointError,
    a user error); a .ply file or a folder of them -> a :class:`PlySource` (every header checked
    first: GaussianPlyError, a user error), played at ``fps`` if given (else the folder's
    manifest.json's rate, else 30); ``"demo"`` -> the built-in synthetic scene."""
    if str(path) == DEMO:
        return SyntheticSource(num_gaussians=demo_gaussians, frames=120, image_size=(640, 480), num_cameras=6)
    p = Path(path)
    if is_ply_input(p):
        from atgs.viewer.ply_source import PlySource

        if p.is_dir() and (p / "ckpt.pt").is_file() and not any(p.glob("*.ply")):
            raise ViewerError(f"{p}: a training run, not a folder of .ply files; pass {p / 'ckpt.pt'}")

        return PlySource.open(p, fps)
    if fps is not None:
        raise ViewerError(f"--fps {fps}: only for PLY input; a checkpoint plays at its own frame rate")
    if not p.is_file():
        raise ViewerError(f"{p}: checkpoint not found; pass the ckpt.pt written by atgs-train, a 3DGS .ply file, "
                          "a folder of per-frame .ply files (atgs-export), or 'demo'")
    from atgs.checkpoint import load_model

    return load_model(p)
