"""Input checks for :func:`atgs.render.rasterize`: one clear error naming the bad argument."""

from __future__ import annotations

import numpy as np
import torch


class RasterInputError(ValueError):
    """A rasterize() argument has the wrong shape, dtype, device or value."""


def _fail(name: str, problem: str, fix: str) -> None:
    raise RasterInputError(f"rasterize(): argument '{name}' {problem}; {fix}")


def as_tensor(value: object, name: str, like: torch.Tensor) -> torch.Tensor:
    """Accept numpy arrays / sequences for camera inputs; convert to ``like``'s dtype/device."""
    if isinstance(value, torch.Tensor):
        return value
    if isinstance(value, (np.ndarray, list, tuple)):
        return torch.as_tensor(np.asarray(value, dtype=np.float64), dtype=like.dtype, device=like.device)
    _fail(name, f"has type {type(value).__name__}", "pass a torch.Tensor (or numpy array)")
    raise AssertionError  # unreachable


def check_inputs(
    tensors: dict[str, torch.Tensor], width: object, height: object
) -> tuple[int, int]:
    """Validate shapes, dtypes, devices and values; return (width, height) as ints."""
    for name, dim in (("width", width), ("height", height)):
        if isinstance(dim, bool) or not isinstance(dim, (int, np.integer)) or int(dim) < 1:
            _fail(name, f"is {dim!r}", "pass a positive int (pixels)")
    for name, t in tensors.items():
        if not isinstance(t, torch.Tensor):
            _fail(name, f"has type {type(t).__name__}", "pass a torch.Tensor")
    means = tensors["means"]
    if means.ndim != 2 or means.shape[1] != 3:
        _fail("means", f"has shape {tuple(means.shape)}", "expected (N, 3)")
    n = means.shape[0]
    expected = {
        "quats": (n, 4), "scales": (n, 3), "opacities": (n,), "colors": (n, 3),
        "viewmat": (4, 4), "K": (3, 3), "background": (3,),
    }  # fmt: skip
    for name, shape in expected.items():
        if name in tensors and tuple(tensors[name].shape) != shape:
            hint = " (opacities must be 1-D, not (N, 1))" if name == "opacities" else ""
            _fail(name, f"has shape {tuple(tensors[name].shape)}", f"expected {shape}{hint}")
    if means.dtype not in (torch.float32, torch.float64):
        _fail("means", f"has dtype {means.dtype}", "use torch.float32 (or float64 with backend='torch')")
    for name, t in tensors.items():
        if t.dtype != means.dtype:
            _fail(name, f"has dtype {t.dtype} but means has {means.dtype}", "use one float dtype for all inputs")
        if t.device != means.device:
            _fail(name, f"is on {t.device} but means is on {means.device}", "move all inputs to one device")
    # Value checks run in numpy on CPU tensors: torch would fork-join its thread pool for each
    # of them, which costs milliseconds per op on a busy 2-core machine.
    for name, t in tensors.items():
        if not _all_finite(t):
            _fail(name, "contains NaN or inf", "check the values that produced it")
    if n:
        op, sc = _values(tensors["opacities"]), _values(tensors["scales"])
        if float(op.min()) < 0 or float(op.max()) > 1:
            _fail("opacities", "has values outside [0, 1]", "apply a sigmoid (or clamp) first")
        if float(sc.min()) < 0:
            _fail("scales", "has negative values", "pass linear standard deviations (e.g. exp(log_scales))")
    K = tensors["K"].detach()
    if not (float(K[0, 0]) > 0 and float(K[1, 1]) > 0):
        _fail("K", f"has fx={float(K[0, 0])}, fy={float(K[1, 1])}", "focal lengths must be positive")
    return int(width), int(height)


def _values(t: torch.Tensor) -> np.ndarray | torch.Tensor:
    t = t.detach()
    return t.numpy() if t.device.type == "cpu" else t


def _all_finite(t: torch.Tensor) -> bool:
    v = _values(t)
    if isinstance(v, np.ndarray):
        return bool(np.isfinite(v).all())
    return bool(torch.isfinite(v).all())
