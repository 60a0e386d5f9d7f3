"""The one public entry point: :func:`rasterize`, which validates inputs and picks a backend."""

from __future__ import annotations

import warnings
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
import torch

from atgs.render.constants import NEAR
from atgs.render.environment import EnvironmentMap
from atgs.render.projection import project
from atgs.render.reference import rasterize_reference
from atgs.render.types import RasterOutput
from atgs.render.validate import RasterInputError, as_tensor, check_inputs, check_near

if TYPE_CHECKING:
    from atgs.cameras import Camera
    from atgs.gaussians import Gaussians

BACKENDS = ("auto", "cpu", "torch", "cuda")


def rasterize(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmat: torch.Tensor | np.ndarray,
    K: torch.Tensor | np.ndarray,
    width: int,
    height: int,
    background: torch.Tensor | np.ndarray | None = None,
    backend: str = "auto",
    near: float = NEAR,
) -> RasterOutput:
    """Render N 3D Gaussians into a ``height x width`` image.

    means (N,3); quats (N,4) as (w,x,y,z), any norm; scales (N,3) linear; opacities (N,) in
    [0,1]; colors (N,3); viewmat (4,4) world-to-camera, OpenCV axes; K (3,3) pinhole
    intrinsics, pixel centers at +0.5; background (3,), (height, width, 3) (one colour per
    pixel, e.g. an environment map's, composited as ``C + T * background``) or None (black).
    backend: "cpu" (compiled C++/OpenMP, float32), "torch" (slow dense reference, any float
    dtype), "cuda" (gsplat; tested on a GPU only), "auto" (cuda if the tensors are on a GPU and
    gsplat imports, else cpu if the extension builds, else torch with a warning).
    near: Gaussians whose view-space z is at or below it are culled, on every backend (a
    model's renders pass its own, ``ATGSModel.near``; the default is gsplat's 0.01).
    Gradients flow to means, quats, scales, opacities, colors (and background); the "torch"
    backend also differentiates viewmat and K.
    """
    if backend not in BACKENDS:
        raise RasterInputError(f"rasterize(): argument 'backend' is {backend!r}; choose one of {BACKENDS}")
    if not isinstance(means, torch.Tensor):
        raise RasterInputError(f"rasterize(): argument 'means' has type {type(means).__name__}; pass a torch.Tensor")
    near = check_near(near)
    viewmat = as_tensor(viewmat, "viewmat", means)
    K = as_tensor(K, "K", means)
    if background is None:
        background = torch.zeros(3, dtype=means.dtype, device=means.device)
    background = as_tensor(background, "background", means)
    if background.dim() == 3:  # per pixel: render over black, then add T * background
        out = rasterize(means, quats, scales, opacities, colors, viewmat, K, width, height, None, backend, near)
        if tuple(background.shape) != tuple(out.image.shape):
            raise RasterInputError(f"rasterize(): argument 'background' has shape {tuple(background.shape)}; "
                                   f"expected (3,) or {tuple(out.image.shape)} (height, width, 3)")
        return replace(out, image=out.image + (1.0 - out.alpha)[..., None] * background)
    tensors = dict(
        means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
        viewmat=viewmat, K=K, background=background,
    )  # fmt: skip
    width, height = check_inputs(tensors, width, height)
    chosen = _choose_backend(backend, means)
    if chosen == "torch":
        return _rasterize_torch(**tensors, width=width, height=height, near=near)
    if chosen == "cpu":
        from atgs.render.cpu import rasterize_cpu

        return rasterize_cpu(**tensors, width=width, height=height, near=near)
    from atgs.render.cuda import rasterize_cuda

    return rasterize_cuda(**tensors, width=width, height=height, near=near)


def rasterize_gaussians(
    gaussians: "Gaussians",
    camera: "Camera",
    background: "torch.Tensor | np.ndarray | EnvironmentMap | None" = None,
    backend: str = "auto",
    near: float = NEAR,
) -> RasterOutput:
    """Convenience wrapper: render an :class:`atgs.gaussians.Gaussians` through an
    :class:`atgs.cameras.Camera` (pinhole part only; prepared scenes are undistorted).
    ``background`` may also be an :class:`~atgs.render.environment.EnvironmentMap`: each pixel
    then shows the map's colour in its direction. ``near``: as in :func:`rasterize` (a model's
    Gaussians: the model's ``near``)."""
    if isinstance(background, EnvironmentMap):
        background = background.image(camera, gaussians.means.device, gaussians.means.dtype)
    return rasterize(
        *gaussians.as_tuple(), camera.w2c, camera.K, camera.width, camera.height,
        background=background, backend=backend, near=near,
    )  # fmt: skip


def warm_up(device: torch.device | str = "cpu", backend: str = "auto") -> str:
    """Render and back-propagate one Gaussian on ``device``; returns the backend that ran.

    The first call of a backend can take minutes: the CPU extension compiles on first use, and
    gsplat compiles its CUDA kernels on its first rasterization. A trainer calls this while it
    sets up, so that a time budget (``atgs-train --train.minutes``) is not spent compiling."""
    device = torch.device(device)
    means = torch.tensor([[0.0, 0.0, 2.0]], device=device, requires_grad=True)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], device=device)
    scales = torch.full((1, 3), 0.1, device=device)
    opacities = torch.full((1,), 0.5, device=device)
    colors = torch.full((1, 3), 0.5, device=device)
    K = np.array([[8.0, 0.0, 4.0], [0.0, 8.0, 4.0], [0.0, 0.0, 1.0]])
    out = rasterize(means, quats, scales, opacities, colors, np.eye(4), K, 8, 8, backend=backend)
    out.image.sum().backward()
    return out.backend


def _choose_backend(backend: str, means: torch.Tensor) -> str:
    if backend != "auto":
        if backend == "cpu" and means.device.type != "cpu":
            raise RasterInputError(f"rasterize(): backend 'cpu' needs CPU tensors, got {means.device}; call .cpu()")
        return backend
    if means.device.type == "cuda":
        from atgs.render.cuda import gsplat_available

        if gsplat_available():
            return "cuda"
        return "torch"
    from atgs.render.cpu import cpu_backend_error

    error = cpu_backend_error()
    if error is None:
        return "cpu"
    warnings.warn(
        f"atgs.render: the compiled CPU rasterizer is unavailable ({error}); "
        "falling back to the slow torch reference",
        RuntimeWarning,
        stacklevel=3,
    )
    return "torch"


def _rasterize_torch(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    background: torch.Tensor,
    width: int,
    height: int,
    near: float = NEAR,
) -> RasterOutput:
    proj = project(means, quats, scales, viewmat, K, width, height, near)
    image, alpha, depth, depth_sq = rasterize_reference(
        proj.means2d, proj.conics, opacities, colors, proj.depths, proj.radii, width, height, background
    )
    return RasterOutput(image, alpha, depth, depth_sq, proj.means2d, proj.radii, backend="torch")
