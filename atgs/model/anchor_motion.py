"""Anchor motion (not in the paper; docs/model.md, "Anchor motion").

A per-keyframe anchor stands for content where it was at its keyframe. Between keyframes the
paper leaves all change to the temporal hash grids, which train slowly: in CPU budgets the
renders barely changed within a keyframe window and moving objects blurred, and every anchor of
the window stayed fully visible, so objects of the neighbouring keyframes showed as ghosts and
anchors popped in and out at window switches. Two per-anchor parameters address this directly:

- a *fade*: the anchor's Gaussians are weighted by ``exp(-d^2 / (2 w^2))``, d the distance in
  keyframe intervals from the frame to the anchor's keyframe and w a learned width (log stored),
  capped so that an anchor has faded below 1/255 by the first frame outside its window (no
  popping);
- a *velocity*: the anchor's Gaussians move by ``d * velocity`` (world units per keyframe
  interval), so the anchors of two neighbouring keyframes meet where the object is.

Static anchors (keyframe ``STATIC``) neither fade nor move. Anchors whose fade is below the
opacity cut are not decoded at all: their Gaussians could not reach 1/255 alpha anywhere.
"""

from __future__ import annotations

import math

import torch

from atgs.timeline import Timeline

# Tables of per-anchor motion parameters (rows follow the anchors).
MOTION_TABLES = ("anchor_velocity", "anchor_fade")

# Below this fade weight an anchor is not decoded (used when the opacity cut is 0).
MIN_FADE = 1.0 / 255.0


# d / w at which the fade reaches 1/256, below one 8-bit level
_LEVEL = math.sqrt(2.0 * math.log(256.0))


def max_fade_width(timeline: Timeline) -> float:
    """Largest fade width (keyframe intervals) of ``timeline``'s window: an anchor leaves the window
    when the nearest keyframe is more than h = W // 2 away, i.e. at a distance over h + 1/2 from
    its keyframe's ideal position, less half a frame of keyframe rounding; there the widest fade
    has fallen to 1/256. No cap without a window (W = 0) or with W = 1 (one keyframe at a time
    switches anchors whatever their fade) or with a single keyframe."""
    K, F, W = timeline.num_keyframes, timeline.num_frames, timeline.window
    h = W // 2
    if W == 0 or h == 0 or K <= 1 or F <= 1:
        return math.inf
    rounding = 0.0 if (F - 1) % (K - 1) == 0 else min(0.5, 0.5 * (K - 1) / (F - 1))
    return (h + 0.5 - rounding) / _LEVEL


def initial_fade(width: float, timeline: Timeline) -> float:
    """The stored (log) fade of a new anchor."""
    return math.log(max(MIN_FADE_WIDTH, min(float(width), max_fade_width(timeline))))


def keyframe_distance(timeline: Timeline, frame: int, keyframe: torch.Tensor) -> torch.Tensor:
    """Signed distance (A,) in keyframe intervals from ``frame`` to the frame of each anchor's
    keyframe; 0 for static anchors (keyframe < 0) and for a single keyframe."""
    K, F = timeline.num_keyframes, timeline.num_frames
    if K <= 1 or F <= 1:
        return torch.zeros(keyframe.shape, dtype=torch.float32, device=keyframe.device)
    frames = torch.tensor(timeline.keyframe_frames(), dtype=torch.float32, device=keyframe.device)
    kf_frame = frames[keyframe.clamp_min(0)]
    d = (float(frame) - kf_frame) * ((K - 1) / (F - 1))
    return torch.where(keyframe >= 0, d, torch.zeros_like(d))


# Narrowest fade width (keyframe intervals): a width that underflows to 0 would make the weight of
# an anchor at its own keyframe 0/0; at this width it is 1 there and ~0 one frame away.
MIN_FADE_WIDTH = 1e-3


def fade_weight(log_width: torch.Tensor, distance: torch.Tensor, max_width: float) -> torch.Tensor:
    """Fade weights (A,) from stored log widths (A, 1) and keyframe distances (A,), the widths
    clamped to [MIN_FADE_WIDTH, ``max_width``] (:func:`max_fade_width`)."""
    w = torch.exp(log_width[:, 0]).clamp(min=MIN_FADE_WIDTH, max=max_width)
    return torch.exp(-0.5 * (distance / w) ** 2)


def faded_and_moved(means: torch.Tensor, opacities: torch.Tensor, weights: torch.Tensor,
                    velocity: torch.Tensor | None, distance: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """The Gaussians (means (A, q, 3), opacities (A, q)) of A anchors with fade ``weights`` (A,)
    and, if given, ``velocity`` (A, 3) at keyframe ``distance`` (A,): (means moved by
    ``distance * velocity``, opacities times the weights, that shift (A, q, 3) or None)."""
    opacities = opacities * weights[:, None]
    if velocity is None:
        return means, opacities, None
    shift = (velocity * distance[:, None])[:, None, :].expand(-1, means.shape[1], -1)
    return means + shift, opacities, shift
