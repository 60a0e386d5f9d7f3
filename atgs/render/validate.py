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


def check_near(near: object) -> float:
    """The near plane as a float: finite and > 0 (a Gaussian at z <= near is culled)."""
    if isinstance(near, bool) or not isinstance(near, (int, float, np.floating, np.integer)) or not 0 < near < np.inf:
        _fail("near", f"is {near!r}", "pass a finite number > 0 (view-space z, in scene units)")
    return float(near)


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
    # Value checks: in numpy on CPU tensors (torch would fork-join its thread pool for each of
    # them, which costs milliseconds per op on a busy 2-core machine); on a GPU all in one
    # device-to-host read instead of one synchronisation per check.
    ok = host_value_flags(tensors, n) if means.device.type == "cpu" else device_value_flags(tensors, n)
    for name in tensors:
        if not ok[f"finite {name}"]:
            _fail(name, "contains NaN or inf", "check the values that produced it")
    if n and not ok["opacities in [0, 1]"]:
        _fail("opacities", "has values outside [0, 1]", "apply a sigmoid (or clamp) first")
    if n and not ok["scales >= 0"]:
        _fail("scales", "has negative values", "pass linear standard deviations (e.g. exp(log_scales))")
    if not ok["focal lengths > 0"]:
        K = tensors["K"].detach()
        _fail("K", f"has fx={float(K[0, 0])}, fy={float(K[1, 1])}", "focal lengths must be positive")
    return int(width), int(height)


def host_value_flags(tensors: dict[str, torch.Tensor], n: int) -> dict[str, bool]:
    """The value checks of CPU tensors (numpy), named as in :func:`device_value_flags`."""
    v = {name: t.detach().cpu().numpy() for name, t in tensors.items()}
    ok = {f"finite {name}": bool(np.isfinite(a).all()) for name, a in v.items()}
    if n:
        op = v["opacities"]
        ok["opacities in [0, 1]"] = bool(op.min() >= 0 and op.max() <= 1)
        ok["scales >= 0"] = bool(v["scales"].min() >= 0)
    ok["focal lengths > 0"] = bool(v["K"][0, 0] > 0 and v["K"][1, 1] > 0)
    return ok


def device_value_flags(tensors: dict[str, torch.Tensor], n: int) -> dict[str, bool]:
    """The value checks computed where the tensors live and read back at once (True: passed)."""
    checks = {f"finite {name}": torch.isfinite(t.detach()).all() for name, t in tensors.items()}
    if n:
        op, sc = tensors["opacities"].detach(), tensors["scales"].detach()
        checks["opacities in [0, 1]"] = (op.min() >= 0) & (op.max() <= 1)
        checks["scales >= 0"] = sc.min() >= 0
    K = tensors["K"].detach()
    checks["focal lengths > 0"] = (K[0, 0] > 0) & (K[1, 1] > 0)
    return dict(zip(checks, torch.stack(list(checks.values())).tolist()))
