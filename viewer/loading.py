"""Open what the viewer plays: a checkpoint (through the model API) or the built-in demo scene."""

from __future__ import annotations

from pathlib import Path

from atgs.viewer.errors import ViewerError
from atgs.viewer.source import GaussianSource, SyntheticSource

DEMO = "demo"  # `atgs-view demo` plays the built-in synthetic scene (no checkpoint needed)


def load_source(path: str | Path, demo_gaussians: int = 20000) -> GaussianSource:
    """A checkpoint path -> the loaded model (``atgs.load``: a bad file raises CheckpointError,
    a user error); ``"demo"`` -> the built-in synthetic scene."""
    if str(path) == DEMO:
        return SyntheticSource(num_gaussians=demo_gaussians, frames=120, image_size=(640, 480), num_cameras=6)
    p = Path(path)
    if not p.is_file():
        raise ViewerError(f"{p}: checkpoint not found; pass the ckpt.pt written by atgs-train (or 'demo')")
    from atgs.checkpoint import load_model

    return load_model(p)
