"""Which anchors a training view needs: a bound on each anchor's Gaussians, tested against frusta.

Training decodes only the anchors whose Gaussians can reach the training camera; evaluation and
the player decode every anchor. The two agree only if the test never drops an anchor one of whose
Gaussians the rasterizer would draw. An anchor's centre says little: on a capture-stage dome the
cameras see each other, and the points on a camera's body sit just behind its lens while their
Gaussians reach in front of it. So each anchor carries its *reach*, the radius of a sphere about
its (moved) centre that holds every Gaussian out to the rasterizer's 3-sigma cut-off, and the
test is sphere against frustum, with the rasterizer's near plane.

The reach is measured, not derived (the offsets are an unbounded MLP output): every decode
records the reach of the anchors it decoded, and :meth:`AnchorReach.refresh` measures the anchors
no decode has seen since the last refresh (the decoder and grids they share keep changing).
Until an anchor is measured its reach is unknown and it is never culled. Between refreshes the
bound is the larger of the last refreshed reach and anything measured since, times ``SAFETY``.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from atgs.cameras import Camera, to_camera_frame
from atgs.render.constants import NEAR, RADIUS_SIGMAS

SAFETY = 1.25  # the bound's slack for what the shared decoder changes between measurements
UNKNOWN = -1.0  # reach not measured yet: the anchor is never culled
REFRESH_STEPS = 100  # the trainer refreshes the reach of anchors no view decoded this often


def gaussian_reach(means: torch.Tensor, scales: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
    """(A,) the radius about ``centre`` (A, 3) holding the q Gaussians (A, q, 3) of each anchor out
    to the rasterizer's cut-off (RADIUS_SIGMAS standard deviations along the longest axis)."""
    d = (means - centre[:, None, :]).norm(dim=-1) + RADIUS_SIGMAS * scales.amax(dim=-1)
    return d.amax(dim=1)


def spheres_in_frustum(centres: torch.Tensor, radii: torch.Tensor, cam: Camera, margin: float,
                       near: float = NEAR) -> torch.Tensor:
    """(A,) True where a sphere may reach ``cam``'s image grown by ``margin`` of its size on each
    side: in front of the near plane (the model's, that its renders cull with) and inside all four
    side planes, each by its radius (a conservative test: spheres near a corner may pass). With
    radius 0 it is the centre's test."""
    p = to_camera_frame(cam, centres)
    x, y, z = p.unbind(1)
    ok = z + radii > near
    mw, mh = margin * cam.width, margin * cam.height
    # side planes x/z = a through the camera centre, as signed distances
    for coord, lo, hi, f, c in ((x, -mw, cam.width + mw, cam.fx, cam.cx), (y, -mh, cam.height + mh, cam.fy, cam.cy)):
        a_lo, a_hi = (lo - c) / f, (hi - c) / f
        ok &= (coord - a_lo * z) / (1.0 + a_lo**2) ** 0.5 > -radii
        ok &= (a_hi * z - coord) / (1.0 + a_hi**2) ** 0.5 > -radii
    return ok


class AnchorReach:
    """Per-anchor reach (rows follow the model's anchors): ``settled`` from the last refresh and
    ``recent``, the largest measured since (UNKNOWN where none)."""

    def __init__(self, n: int, device: torch.device) -> None:
        self.settled = torch.full((n,), UNKNOWN, device=device)
        self.recent = torch.full((n,), UNKNOWN, device=device)

    def bound(self, rows: torch.Tensor | None = None) -> torch.Tensor:
        """(A,) the culling radius; +inf where the reach is unknown."""
        s, r = (self.settled, self.recent) if rows is None else (self.settled[rows], self.recent[rows])
        b = torch.maximum(s, r)
        return torch.where(b < 0, torch.full_like(b, float("inf")), SAFETY * b)

    def record(self, rows: torch.Tensor, reach: torch.Tensor) -> None:
        self.recent[rows] = torch.maximum(self.recent[rows], reach.detach().float())

    def stale(self) -> torch.Tensor:
        """Ids of the anchors not measured since the last refresh."""
        return (self.recent < 0).nonzero().squeeze(1)

    def settle(self) -> None:
        """End a refresh: what was measured since the last one becomes the settled reach."""
        known = self.recent >= 0
        self.settled = torch.where(known, self.recent, self.settled)
        self.recent = torch.full_like(self.recent, UNKNOWN)

    def append(self, n: int) -> None:
        extra = torch.full((n,), UNKNOWN, device=self.settled.device)
        self.settled, self.recent = torch.cat([self.settled, extra]), torch.cat([self.recent, extra])

    def keep(self, keep: torch.Tensor) -> None:
        self.settled, self.recent = self.settled[keep].contiguous(), self.recent[keep].contiguous()

    def to(self, device: torch.device) -> None:
        self.settled, self.recent = self.settled.to(device), self.recent.to(device)


def visible_anchors(centres: torch.Tensor, radii: torch.Tensor, cams: Sequence[Camera],
                    margin: float, near: float = NEAR) -> torch.Tensor:
    """(A,) True where an anchor's sphere may reach any of ``cams`` beyond ``near``."""
    seen = spheres_in_frustum(centres, radii, cams[0], margin, near)
    for c in cams[1:]:
        seen |= spheres_in_frustum(centres, radii, c, margin, near)
    return seen
