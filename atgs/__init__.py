"""ATGS: Anchored Temporal Gaussian Splatting for long volumetric video."""

from pathlib import Path as _Path

from atgs.cameras import Camera
from atgs.gaussians import Gaussians

__version__ = "0.1.0"

# The player (viewer/) and its shaders (shaders/) sit beside this folder in the repository and
# install as atgs.viewer and atgs.shaders (package-dir in pyproject.toml). In a source checkout
# used without installing (PYTHONPATH=<repo>), let ``import atgs.viewer`` find them there too;
# an installed atgs has its own atgs/viewer and this does nothing.
_checkout = _Path(__file__).resolve().parent.parent
if not (_Path(__file__).parent / "viewer").is_dir() and (_checkout / "viewer" / "__init__.py").is_file() \
        and (_checkout / "pyproject.toml").is_file():
    __path__.append(str(_checkout))  # noqa: F821 - the package's module search path


def load(path, device="cpu"):
    """Load a trained checkpoint ``ckpt.pt`` and return the model (see :mod:`atgs.model`) on
    ``device`` ("cpu", "cuda", a torch.device); checkpoints load on any device."""
    from atgs.checkpoint import load_model  # deferred: keeps `import atgs` light

    return load_model(path, device=device)


__all__ = ["Camera", "Gaussians", "load", "__version__"]
