"""Random static anchors outside the space the keyframe points show to be empty.

The CPU presets add anchors sampled in the scene bounds (``ModelConfig.random_anchors``) so that
surfaces the sparse points miss can still be learned. Sampled uniformly in the box, many land
between the cameras and the surfaces they see; a camera whose view they cross is then fitted
with them, and a camera held out from training sees them as floaters (on the real N3DV frame
dropping the Gaussians within 5 m of that camera raised its PSNR by 4.6 dB; docs/model.md).
So samples in the space the points prove empty (atgs.geometry.free_space) are rejected, and so are
samples no training camera sees: no image would ever train them.
"""

from __future__ import annotations

import torch

from atgs.geometry.free_space import FreeSpace

OVERSAMPLE = 8  # candidates drawn per wanted anchor, in rounds, before giving up


def random_anchor_points(n: int, box: torch.Tensor, free: FreeSpace | None, generator: torch.Generator
                         ) -> torch.Tensor:
    """Up to ``n`` points uniform in ``box`` (2,3) that ``free`` keeps (:meth:`FreeSpace.kept`:
    seen by a camera, not in empty space; fewer where little space is left after OVERSAMPLE x n
    candidates); ``free`` None: plain uniform samples."""
    lo, size = box[0].float(), (box[1] - box[0]).float()
    if free is None or not free.cameras:
        return lo + torch.rand(n, 3, generator=generator, device=generator.device) * size
    kept: list[torch.Tensor] = []
    total = 0
    for _ in range(OVERSAMPLE):
        cand = lo + torch.rand(n, 3, generator=generator, device=generator.device) * size
        ok = torch.as_tensor(free.kept(cand.double().cpu().numpy()), device=cand.device)
        kept.append(cand[ok])
        total += int(ok.sum())
        if total >= n:
            break
    return torch.cat(kept)[:n]
