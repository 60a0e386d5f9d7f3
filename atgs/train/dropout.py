"""Gaussian dropout during training (DropGaussian, Park et al., CVPR 2025; not in the ATGS paper).

Each step hides a random fraction ``r`` of the decoded Gaussians from the rasterizer and scales
the opacity of the rest by ``1 / (1 - r)``, so a pixel's expected coverage stays what it was. A
Gaussian behind others then gets seen and gradients in some steps, and no small set of Gaussians
can fit one training view on its own: the published remedy for over-fitting the few views a
sparse rig gives. ``r`` grows linearly from 0 to its maximum over the run; evaluation, the viewer
and exports render every Gaussian with its own opacity.
"""

from __future__ import annotations

from dataclasses import replace

import torch

from atgs.gaussians import Gaussians


def drop_rate(max_rate: float, step: int, total_steps: int) -> float:
    """The rate at ``step``: ``max_rate * step / total_steps``, capped at ``max_rate``."""
    if max_rate <= 0 or total_steps <= 0:
        return 0.0
    return max_rate * min(1.0, step / total_steps)


def render_generator(seed: int, step: int, view: int, camera: int, device: torch.device | str) -> torch.Generator:
    """The generator of one render's draw: a function of the run's seed and the render's place
    (step, view of the step, camera of the view), not of what was drawn before it. So workers
    that share a step's renders drop what one process would, and a resumed run what the
    uninterrupted one did."""
    mixed = ((seed * 1_000_003 + step) * 65_537 + view) * 257 + camera
    return torch.Generator(device=device).manual_seed(mixed % 2**63)


def drop_gaussians(g: Gaussians, rate: float, generator: torch.Generator, ids: torch.Tensor | None = None,
                   num_ids: int = 0) -> Gaussians:
    """``g`` with a random ``rate`` of its Gaussians at zero opacity and the others' opacities
    divided by ``1 - rate`` (at most 1). Shapes stay as they are (the densification statistics
    index the decoded Gaussians); the draw is on ``generator``'s device, so a seed drops the same Gaussians
    on every device. ``ids``: each Gaussian's identity in ``0..num_ids - 1`` (the model's
    anchor * q + slot): one draw per identity, so a Gaussian is dropped or kept whichever others
    were decoded with it (a worker's culling may decode a few anchors more or fewer than one
    process's); None: one draw per Gaussian of ``g``, in order."""
    if rate <= 0 or len(g) == 0:
        return g
    if not rate < 1:
        raise ValueError(f"a drop rate must be below 1, got {rate}")
    if ids is None:
        keep = torch.rand(len(g), generator=generator, device=generator.device) >= rate
    else:
        draws = torch.rand(num_ids, generator=generator, device=generator.device)
        keep = draws.index_select(0, ids.to(draws.device)) >= rate
    scale = keep.to(device=g.opacities.device, dtype=g.opacities.dtype) / (1.0 - rate)
    # capped at 1 (the rasterizer's domain; its alpha is capped below that anyway)
    return replace(g, opacities=(g.opacities * scale).clamp(max=1.0))
