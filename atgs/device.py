"""Where tensors live: the ``--device auto|cpu|cuda`` rule of ``atgs-train`` and ``atgs-view``.

"cpu" is always the CPU. "cuda" needs a CUDA device that torch sees and, for training, gsplat
(the GPU rasterizer; without it a CUDA model would fall back to the slow torch reference
rasterizer); without them it is a one-line error naming the fix. "auto" picks CUDA exactly when
"cuda" would work, else the CPU.
"""

from __future__ import annotations

from typing import Literal, get_args

import torch

from atgs.errors import UserError

DeviceName = Literal["auto", "cpu", "cuda"]
DEVICE_NAMES: tuple[str, ...] = get_args(DeviceName)


class DeviceError(UserError, ValueError):
    """A device that cannot be used here; the message names the fix."""


def cuda_problem(need_gsplat: bool) -> str | None:
    """Why CUDA cannot be used here, as the end of a one-line message (None: it can)."""
    if not torch.cuda.is_available():
        return ("torch sees no CUDA device (a CPU-only torch build, or no GPU/driver); "
                "install a CUDA build of torch, or use --device cpu")
    if need_gsplat:
        from atgs.render.cuda import gsplat_import_error

        error = gsplat_import_error()
        if error is not None:
            return (f"gsplat, the GPU rasterizer, is not usable ({error}); pip install gsplat (its first use "
                    "compiles CUDA kernels with nvcc: install the CUDA toolkit of torch's CUDA version), "
                    "or use --device cpu")
    return None


def resolve_device(name: str, need_gsplat: bool = False) -> torch.device:
    """The device of ``--device name``; ``need_gsplat``: CUDA also needs the GPU rasterizer."""
    if name not in DEVICE_NAMES:
        raise DeviceError(f"--device {name}: choose one of {', '.join(DEVICE_NAMES)}")
    if name == "cpu":
        return torch.device("cpu")
    problem = cuda_problem(need_gsplat)
    if problem is None:
        return torch.device("cuda")
    if name == "cuda":
        raise DeviceError(f"--device cuda: {problem}")
    return torch.device("cpu")


def usable_device(device: torch.device | str) -> torch.device:
    """``device`` (a torch device or its name, as ``atgs.load`` takes it) as a torch.device; a
    CUDA device that torch cannot see is a one-line error."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise DeviceError(f"device {device!r} is not a torch device; use 'cpu' or 'cuda'") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise DeviceError(f"device {device!r}: torch sees no CUDA device (a CPU-only torch build, or no "
                          "GPU/driver); load with device='cpu'")
    return dev


def auto_fallback_note(name: str, device: torch.device, need_gsplat: bool) -> str | None:
    """Why ``--device auto`` chose the CPU although torch sees a GPU (None: it did not), so that
    a user with a GPU learns why it sits idle (gsplat missing, or no nvcc to build it)."""
    if name != "auto" or device.type != "cpu" or not torch.cuda.is_available():
        return None
    problem = cuda_problem(need_gsplat)
    return None if problem is None else f"a CUDA device is present, but this runs on the CPU: {problem.split(';')[0]}"


def device_description(device: torch.device) -> str:
    """A short name of ``device`` for messages ("cuda (NVIDIA H100 80GB HBM3)", "cpu")."""
    if device.type == "cuda":
        return f"cuda ({torch.cuda.get_device_name(device)})"
    return str(device)
