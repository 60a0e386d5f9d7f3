"""A dataset's poses checked against its own images, before anything slow runs.

Hand-written calibration files get their conventions wrong in ways that no number in the file
betrays: a public Dynamic 3D Gaussians capture stores camera-to-world matrices under its
``w2c`` key, in a mirrored world. A mirrored world is read by mirroring it back
(:func:`proper_world`); which way round the matrices go is decided here from the images. SIFT
matches between the training cameras' first frames, verified by COLMAP's own two-view RANSAC
(which knows nothing of the poses), must lie on the epipolar lines that the poses predict.

- The reading as given is kept when most matches agree with it.
- The other reading (the matrices inverted) replaces it only when the matches agree with that
  one and not with the given one; one line says so.
- Wide-baseline rigs (three cameras around a room) give SIFT too few matches to judge; there
  the rig's geometry decides: a rig looks at a common region, so the other reading is taken when
  under the given one the training cameras look away from one another and under the other they
  all see where they point. (A ring centred on the world's origin looks inwards under both
  readings; there only the matches can tell, and without them the poses are kept as given.)
- When neither reading agrees, the poses are kept with a warning that gives the figures.

Held-out cameras take no part: their images are never read here. The reading chosen from the
training cameras is the file's convention and applies to every camera in it.
"""

from __future__ import annotations

import shutil
import sys
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from PIL import Image

from atgs.cameras import Camera
from atgs.data.colmap_ops import ColmapOptions, verified_pairs
from atgs.data.errors import DataError
from atgs.geometry.projection import project
from atgs.geometry.seen_space import axes_meeting_point

MIRROR_X = np.diag([-1.0, 1.0, 1.0, 1.0])  # the world mirror that makes a left-handed calibration right-handed


@dataclass(frozen=True)
class PoseCheckConfig:
    work_side: int = 1024  # frames are box-downscaled to at most this long side for SIFT
    tolerance_px: float = 4.0  # at the working size: a match agrees within this distance of its epipolar line
    agree: float = 0.5  # share of matches that must agree for a reading to be trusted
    min_matches: int = 40  # fewer verified matches than this over all pairs: too few to judge by


def proper_world(cams: Sequence[Camera], where: Path) -> tuple[list[Camera], np.ndarray | None]:
    """``cams`` with proper rotations, and the world mirror applied (None when none was needed).

    A calibration whose every rotation has determinant -1 lives in a left-handed (mirrored)
    world; it projects exactly as well after mirroring the world's x axis, which is the only
    change made (points given in that world take the same mirror). Some cameras mirrored and
    some not cannot come from one rig: an error."""
    dets = np.array([np.linalg.det(c.w2c[:3, :3]) for c in cams])
    if np.all(dets > 0):
        return list(cams), None
    if np.any(dets > 0):
        flipped = [c.name for c, d in zip(cams, dets) if d < 0]
        raise DataError(f"{where}: the rotations of camera(s) {', '.join(flipped[:6])} are mirror images "
                        "(determinant -1) and the others are not; one rig's calibration is mirrored for all "
                        "cameras or none, so fix those cameras' matrices")
    print(f"note: {where}: every camera's rotation is mirrored (determinant -1): a left-handed world; "
          "reading it with the world's x axis mirrored (the views are unchanged)", file=sys.stderr)
    return [replace(c, w2c=c.w2c @ MIRROR_X) for c in cams], MIRROR_X


def inverted_reading(cam: Camera, mirror: np.ndarray | None) -> Camera:
    """``cam`` with its source matrix read the other way round (camera-to-world for
    world-to-camera and back), then mirrored as the source's world is: mirror . inv(M . mirror) . mirror."""
    F = np.eye(4) if mirror is None else mirror
    return replace(cam, w2c=F @ np.linalg.inv(cam.w2c) @ F)


@dataclass
class Matches:
    """Verified SIFT matches of one pair of cameras: pixel positions (pixel centres at +0.5)."""

    a: int
    b: int
    xy_a: np.ndarray  # (N, 2)
    xy_b: np.ndarray  # (N, 2)


def fundamental(ca: Camera, cb: Camera) -> np.ndarray:
    """F with x_b^T F x_a = 0 for homogeneous pixels of a point seen by both cameras."""
    R = cb.R @ np.linalg.inv(ca.R)
    t = cb.t - R @ ca.t
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return np.linalg.inv(cb.K).T @ tx @ R @ np.linalg.inv(ca.K)


def epipolar_distances(ca: Camera, cb: Camera, xy_a: np.ndarray, xy_b: np.ndarray) -> np.ndarray:
    """Sampson distance (px) of each match from the epipolar geometry of the two cameras; inf
    for a pair without baseline (no epipolar geometry to agree with)."""
    if np.linalg.norm(cb.center - ca.center) <= 1e-9 * (1.0 + np.linalg.norm(ca.center)):
        return np.full(len(xy_a), np.inf)
    F = fundamental(ca, cb)
    xa = np.c_[xy_a, np.ones(len(xy_a))]
    xb = np.c_[xy_b, np.ones(len(xy_b))]
    Fxa, Ftxb = xa @ F.T, xb @ F
    num = np.einsum("ij,ij->i", xb, Fxa) ** 2
    den = Fxa[:, 0] ** 2 + Fxa[:, 1] ** 2 + Ftxb[:, 0] ** 2 + Ftxb[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-300))


def agreement(cams: Sequence[Camera], matches: Sequence[Matches], tolerance_px: float) -> float:
    """Share of all matches within ``tolerance_px`` of their epipolar lines under ``cams``."""
    d = [epipolar_distances(cams[m.a], cams[m.b], m.xy_a, m.xy_b) for m in matches]
    return float(np.mean(np.concatenate(d) <= tolerance_px)) if d else 0.0


def verified_matches(images: Sequence[np.ndarray], work: Path, opts: ColmapOptions) -> list[Matches]:
    """SIFT matches between every pair of ``images`` that COLMAP's two-view RANSAC verified."""
    img_dir = work / "images"
    img_dir.mkdir(parents=True, exist_ok=True)
    names = [f"{i:04d}.png" for i in range(len(images))]
    for name, img in zip(names, images):
        Image.fromarray(img).save(img_dir / name)
    return [Matches(*pair) for pair in verified_pairs(img_dir, names, work / "database.db", opts)]


def _work_camera(cam: Camera, side: int) -> Camera:
    s = min(1.0, side / max(cam.width, cam.height))
    return replace(cam, dist=None) if s == 1.0 else replace(cam, dist=None).scaled(s)


def check_poses(cams: list[Camera], frames: Sequence[np.ndarray | None], mirror: np.ndarray | None, where: Path,
                work: Path, cfg: PoseCheckConfig, opts: ColmapOptions, progress: bool = True,
                by_layout: bool = True) -> list[Camera]:
    """The cameras under the reading of the matrices that the images agree with.

    ``frames[i]``: camera i's first frame, undistorted (as the prepared scene stores it) at the
    camera's full size, or None for a camera that takes no part (held out).

    Evidence, strongest first: the epipolar agreement of verified matches (when there are
    ``min_matches``); then, for wide-baseline rigs where SIFT finds too few, where the rig looks:
    the point nearest every training camera's optical axis must be in view of most of them. That
    second rule is a guess that a rig looks at a common region, used only where ``by_layout``
    (formats written by hand, where the inversion is a common mistake; a program's COLMAP or
    LLFF poses pointing apart are a broken rig, reported as such later). A reading is replaced
    only when the other one is clearly right and the given one clearly wrong; otherwise the poses
    are kept as given, with a warning when the matches disagree with them."""
    used = [i for i, f in enumerate(frames) if f is not None]
    if len(used) < 2:
        return cams
    other = [inverted_reading(c, mirror) for c in cams]
    wcams = [_work_camera(c, cfg.work_side) for c in cams]
    small = [np.asarray(Image.fromarray(frames[i]).resize((wcams[i].width, wcams[i].height), Image.BOX))
             if (wcams[i].width, wcams[i].height) != (cams[i].width, cams[i].height) else frames[i] for i in used]
    try:
        found = verified_matches(small, work, opts)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    matches = [Matches(used[m.a], used[m.b], m.xy_a, m.xy_b) for m in found]
    n, tol = sum(len(m.xy_a) for m in matches), cfg.tolerance_px
    given = agreement(wcams, matches, tol)
    inverted = agreement([inverted_reading(c, mirror) for c in wcams], matches, tol)
    figures = f"{given:.0%} of {n} feature matches within {tol:g} px of their epipolar lines"
    if n >= cfg.min_matches and given >= cfg.agree:
        if progress:
            print(f"poses agree with the images: {figures}", file=sys.stderr)
        return cams
    if n >= cfg.min_matches and inverted >= cfg.agree and inverted >= 2 * given:
        print(f"note: {where}: the poses disagree with the images as world-to-camera matrices ({figures}) and "
              f"agree as camera-to-world ({inverted:.0%}): reading them as camera-to-world", file=sys.stderr)
        return other
    looks_given, looks_inverted = (share_seeing(r, axes_meeting_point(r)) for r in ([cams[i] for i in used],
                                                                                  [other[i] for i in used]))
    if by_layout and looks_given <= 1 / 3 and looks_inverted == 1.0:
        why = (f"too few feature matches to tell: {n}" if n < cfg.min_matches else
               f"the feature matches agree with neither reading: {given:.0%} and {inverted:.0%} of {n}")
        print(f"note: {where}: as world-to-camera matrices the training cameras look away from one another "
              f"({looks_given:.0%} of them see the point nearest their optical axes); as camera-to-world all of "
              f"them do: reading them as camera-to-world ({why})", file=sys.stderr)
        return other
    if n >= cfg.min_matches:
        print(f"warning: {where}: only {figures} (the poses inverted: {inverted:.0%}); if the training views fit "
              "poorly, check that the calibration belongs to these images", file=sys.stderr)
    elif progress:
        print(f"note: {where}: {n} feature matches between the training cameras' first frames, too few to check "
              "the poses against the images; used as given", file=sys.stderr)
    return cams


def share_seeing(cams: Sequence[Camera], p: np.ndarray | None) -> float:
    """Share of ``cams`` with ``p`` in front of them and inside their image (0 without a point)."""
    return 0.0 if p is None else float(np.mean([bool(project(c, p[None]).inside[0]) for c in cams]))
