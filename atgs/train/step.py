"""The types of one training step (atgs.train.trainer): the views it draws, what their
backward passes leave for the update, and what it reports. A partition (atgs.train.partition)
draws the views and exchanges a :class:`StepViews` among several workers."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch


@dataclass
class View:
    """One view of a step: a frame, decoded once, rendered from ``cams`` (training camera indices)."""

    index: int  # in the step's views
    cams: list[int]
    frame: int
    backgrounds: list | None = None  # drawn in advance (several workers); None: drawn at render time


@dataclass
class StepViews:
    """What one step's views leave for the update: all of the step's views in one process, this
    worker's share on several (until the partition's exchange puts everyone's in)."""

    grads: dict[str, list[tuple[torch.Tensor, torch.Tensor]]] = field(default_factory=dict)  # table -> (rows, grad)
    losses: list[torch.Tensor] = field(default_factory=list)  # per render
    psnrs: list[torch.Tensor] = field(default_factory=list)
    n_gauss: int = 0
    bad: bool = False  # a non-finite decode or loss: the step changes nothing
    segments: list[int] = field(default_factory=list)  # of every view of the step
    decoded: list[torch.Tensor] = field(default_factory=list)  # anchors each decode measured the reach of
    totals: tuple[float, float, int, int] | None = None  # all workers' (loss sum, PSNR sum, renders, Gaussians)

    def means(self) -> tuple[float, float, int] | None:
        """(mean loss, mean PSNR, Gaussians per render) of the step's renders; None without any."""
        if self.totals is not None:
            loss, p, n, g = self.totals
            return (loss / n, p / n, g // n) if n else None
        if not self.losses:
            return None
        values = torch.cat([torch.stack(self.losses).double(), torch.stack(self.psnrs).double()]).tolist()
        n = len(self.losses)
        return float(np.mean(values[:n])), float(np.mean(values[n:])), self.n_gauss // n


@dataclass
class StepResult:
    loss: float
    psnr: float
    gaussians: int
    skipped: bool
