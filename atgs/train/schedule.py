"""Learning-rate schedules (SPEC section 1): exponential decay and linear warm-up."""

from __future__ import annotations

import math


def exp_decay(lr_init: float, lr_final: float, step: int, max_steps: int) -> float:
    """Log-linear interpolation from lr_init (step 0) to lr_final (step >= max_steps)."""
    if lr_init <= 0 or lr_final <= 0:
        return lr_init if step < max_steps else lr_final
    p = min(1.0, max(0.0, step / max(1, max_steps)))
    return math.exp(math.log(lr_init) * (1 - p) + math.log(lr_final) * p)


def warmup(step: int, warmup_steps: int, start: float) -> float:
    """Factor growing linearly from ``start`` to 1 over ``warmup_steps`` steps."""
    if warmup_steps <= 0 or step >= warmup_steps:
        return 1.0
    return start + (1.0 - start) * step / warmup_steps
