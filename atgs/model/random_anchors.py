"""Random static anchors outside the space the keyframe points show to be empty.

The CPU presets add anchors sampled in the scene bounds (``ModelConfig.random_anchors``) so that
surfaces the sparse points miss can still be learned. Sampled uniformly in the box, many land
between the cameras and the surfaces they see; a camera whose view they cross is then fitted
with them, and a camera held out from training sees them as floaters (on the real N3DV frame
dropping the Gaussians within 5 m of that camera raised its PSNR by 4.6 dB; docs/model.md).
So samples in the space the points prove empty (atgs.free_space) are rejected, and so are
samples no training camera sees: no image would ever train them.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from atgs.cameras import Camera
from atgs.free_space import MARGIN, carve

OVERSAMPLE = 8  # candidates drawn per wanted anchor, in rounds, before giving up


def random_anchor_points(n: int, box: torch.Tensor, points: torch.Tensor, cameras: Sequence[Camera],
                         generator: torch.Generator, margin: float = MARGIN) -> torch.Tensor:
    """Up to ``n`` points uniform in ``box`` (2,3) that ``carve`` keeps (fewer where little space
    is left after OVERSAMPLE x n candidates; without cameras, plain uniform samples)."""
    lo, size = box[0].float(), (box[1] - box[0]).float()
    if not cameras:
        return lo + torch.rand(n, 3, generator=generator, device=generator.device) * size
    pts = points.detach().double().cpu().numpy()
    kept: list[torch.Tensor] = []
    total = 0
    for _ in range(OVERSAMPLE):
        cand = lo + torch.rand(n, 3, generator=generator, device=generator.device) * size
        ok = torch.as_tensor(carve(cand.double().cpu().numpy(), pts, cameras, margin), device=cand.device)
        kept.append(cand[ok])
        total += int(ok.sum())
        if total >= n:
            break
    return torch.cat(kept)[:n]
