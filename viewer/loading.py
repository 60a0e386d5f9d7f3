"""Open what the viewer plays: a checkpoint (through the model API) or the built-in demo scene."""

from __future__ import annotations

from pathlib import Path

from viewer.errors import ViewerError
from viewer.source import GaussianSource, SyntheticSource

DEMO = "demo"  # `atgs-view demo` plays the built-in synthetic scene (no checkpoint needed)


def open_source(path: str | Path, demo_gaussians: int = 20000) -> GaussianSource:
    """A checkpoint path -> the loaded model; ``"demo"`` -> the built-in synthetic scene."""
    if str(path) == DEMO:
        return SyntheticSource(num_gaussians=demo_gaussians, frames=120, image_size=(640, 480), num_cameras=6)
    p = Path(path)
    if not p.is_file():
        raise ViewerError(f"{p}: checkpoint not found; pass the ckpt.pt written by atgs-train (or 'demo')")
    try:
        from atgs.checkpoint import CheckpointError, load_model
    except ImportError as exc:  # pragma: no cover - only in a broken install
        raise ViewerError(f"cannot import the model package ({exc}); reinstall atgs") from None
    try:
        model = load_model(p)
    except CheckpointError as exc:
        raise ViewerError(_one_line(str(exc))) from None
    except Exception as exc:  # anything else from a damaged file must not become a traceback
        raise ViewerError(f"{p}: cannot load checkpoint ({type(exc).__name__}: {_one_line(str(exc))})") from None
    if model.num_frames < 1:
        raise ViewerError(f"{p}: checkpoint has no frames; re-train or pick another file")
    return model


def _one_line(text: str) -> str:
    lines = [s.strip() for s in text.strip().splitlines() if s.strip()]
    return lines[0] if lines else "unknown error"
