"""ATGS: Anchored Temporal Gaussian Splatting for long volumetric video."""

from atgs.cameras import Camera
from atgs.gaussians import Gaussians

__version__ = "0.1.0"


def load(path, device="cpu"):
    """Load a trained checkpoint ``ckpt.pt`` and return the model (see :mod:`atgs.model`) on
    ``device`` ("cpu", "cuda", a torch.device); checkpoints load on any device."""
    from atgs.checkpoint import load_model  # deferred: keeps `import atgs` light

    return load_model(path, device=device)


__all__ = ["Camera", "Gaussians", "load", "__version__"]
