"""Adaptive resolution: the splatting resolution factor that keeps a frame near a time budget."""

from __future__ import annotations

MIN_SCALE = 0.25  # below this the image is too coarse to be useful and per-splat setup dominates
TARGET_MS = 40.0  # 25 FPS


GROW_BELOW = 0.7  # grow only below 0.7 x target: one 1.1x step (1.21x pixels) stays under it


def next_render_scale(scale: float, draw_ms: float, target_ms: float = TARGET_MS) -> float:
    """The factor (of width and height) for the next frame after a draw of ``draw_ms`` at
    ``scale``: over the target shrink by 0.85, under 0.7x the target grow by 1.1, else keep (the
    band keeps it from oscillating, and it lies below the target, so the frame rate settles at
    or above 1000 / target_ms); clamped to [MIN_SCALE, 1]."""
    if draw_ms > target_ms:
        return max(MIN_SCALE, scale * 0.85)
    if draw_ms < GROW_BELOW * target_ms:
        return min(1.0, scale * 1.1)
    return scale
