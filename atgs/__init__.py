"""ATGS: Anchored Temporal Gaussian Splatting for long volumetric video."""

import re

import torch

# the oldest torch the code runs on (pyproject.toml says the same): torch.serialization.skip_data,
# with which the time partition's checkpoint is written as it arrives (atgs.io.torch_zip), is 2.5's
TORCH_MIN = (2, 5)


def check_torch() -> None:
    """Refuse, in one line, a torch older than :data:`TORCH_MIN` (pip's floor can be bypassed:
    a torch installed before this package, ``--no-deps``), rather than fail mid-run at a save."""
    found = re.match(r"(\d+)\.(\d+)", str(torch.__version__))
    if found and tuple(map(int, found.groups())) < TORCH_MIN:
        need = ".".join(map(str, TORCH_MIN))
        raise ImportError(f"atgs needs torch>={need} (torch.serialization.skip_data, atgs/io/torch_zip.py), but "
                          f"torch {torch.__version__} is installed; upgrade it: pip install 'torch>={need}'")


check_torch()

from atgs.cameras import Camera  # noqa: E402 (after the check: a too old torch stops here, in one line)
from atgs.gaussians import Gaussians  # noqa: E402

__version__ = "0.1.0"


def load(path, device="cpu"):
    """Load a trained checkpoint ``ckpt.pt`` and return the model (see :mod:`atgs.model`) on
    ``device`` ("cpu", "cuda", a torch.device); checkpoints load on any device."""
    from atgs.checkpoint import load_model  # deferred: keeps `import atgs` light

    return load_model(path, device=device)


__all__ = ["Camera", "Gaussians", "load", "__version__"]
