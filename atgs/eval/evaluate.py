"""Evaluation of a model on the held-out cameras of a prepared scene: the one evaluation path.

:func:`evaluate` is a library function (``Trainer.evaluate`` calls it with a frame subset for
periodic and final evaluation; ``atgs-eval`` wraps it): for every selected camera and frame it
renders ``model.gaussians_at_frame(frame)`` with :func:`atgs.render.rasterize_gaussians` from
that camera (culled at the model's near plane, as training rendered), compares with the
ground-truth image and returns per-view rows and a summary. With an output directory it also
writes::

    OUT/
      per_view.csv           camera, frame, psnr, psnr_matched, ssim, dssim1, dssim2, ms_ssim, dssim_ms, lpips
      summary.json           means (overall, per camera), settings, metric definitions
      images/<camera>/<frame:06d>.png   render | ground truth | error, a few frames per camera

The directory is built beside OUT and swapped in only when complete: a failed or interrupted
run leaves a previous OUT untouched.
"""

from __future__ import annotations

import csv
import io
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol

import numpy as np
import torch
from PIL import Image

from atgs.cameras import Camera
from atgs.data.scene import resize_frame
from atgs.errors import UserError
from atgs.io.atomic import atomic_dir
from atgs.eval.exposure_match import add_matched_psnr, view_sums
from atgs.eval.lpips import LPIPS, load_lpips
from atgs.eval.metrics import all_metrics, ms_ssim_levels
from atgs.gaussians import Gaussians
from atgs.progress import progress_bar
from atgs.model.near_plane import near_of
from atgs.render.environment import EnvironmentMap
from atgs.render import rasterize_gaussians
from atgs.render.constants import NEAR
from atgs.timeline import evenly_spaced

METRICS = ("psnr", "psnr_matched", "ssim", "dssim1", "dssim2", "ms_ssim", "dssim_ms", "lpips")
METRIC_DEFINITIONS = {
    "psnr": "10 log10(1 / MSE), MSE over all pixels and channels of the view; averaged over views",
    "psnr_matched": "PSNR after each camera's own gain and bias per colour channel, fitted by least "
                    "squares over all its evaluated views (the exposure a held-out camera's images "
                    "carry, which training cannot learn; atgs/eval/exposure_match.py)",
    "ssim": "Gaussian window 11, sigma 1.5, K1 0.01, K2 0.03, data range 1, zero 'same' padding (3DGS)",
    "dssim1": "(1 - ssim) / 2",
    "dssim2": "(1 - SSIM with data range 2) / 2: scikit-image legacy defaults (7x7 uniform window, "
              "sample covariance), as in SpacetimeGaussians and the ATGS paper's DSSIM2",
    "ms_ssim": "MS-SSIM, 5 scales (fewer for small images, weights renormalised), weights "
               "0.0448 0.2856 0.3001 0.2363 0.1333, valid Gaussian windows, 2x2 average pooling",
    "dssim_ms": "(1 - ms_ssim) / 2 (the DSSIM of 4DGS, Yang et al.)",
    "lpips": "LPIPS v0.1 AlexNet, inputs in [-1,1]; 'unavailable' when its weights are not on disk",
}
UNAVAILABLE = "unavailable"


class EvalError(UserError):
    """Bad evaluation input (cameras, frames, files); the message is one line for the user."""


class EvalModel(Protocol):
    num_frames: int
    cameras: list[Camera]

    def gaussians_at_frame(self, frame: int) -> Gaussians: ...


class EvalScene(Protocol):
    cameras: list[Camera]
    num_frames: int

    @property
    def test_indices(self) -> list[int]: ...

    def image(self, cam_index: int, frame: int) -> np.ndarray: ...


@dataclass
class EvalConfig:
    """What to evaluate and what to write."""

    frames: tuple[int, ...] = ()
    """Frames to evaluate (default: all frames, thinned by --every)."""
    every: int = 1
    """Evaluate every N-th of the selected frames."""
    cameras: tuple[str, ...] = ()
    """Camera names to evaluate (default: the scene's test cameras)."""
    images_per_camera: int = 3
    """Side-by-side render|GT|error PNGs written per camera (evenly spaced frames; 0 = none)."""
    error_gain: float = 4.0
    """Absolute error is multiplied by this before colouring the error panel."""
    lpips: bool = True
    """Compute LPIPS when its weights are on disk (never downloaded)."""
    lpips_backbone: Path | None = None
    """torchvision AlexNet weights (default: the torch hub cache)."""
    lpips_linear: Path | None = None
    """LPIPS v0.1 alex.pth linear heads (default: an installed 'lpips' package)."""
    resolution_scale: float = 1.0
    """Evaluate at this fraction of the scene's resolution (ground truth downsampled with
    Lanczos, as the trainer does); numbers below 1.0 do not compare with full-resolution ones."""
    backend: Literal["auto", "cpu", "torch", "cuda"] = "auto"
    """Rasterizer backend (auto: compiled CPU rasterizer, or gsplat for GPU tensors)."""
    progress: bool = True
    """Show a progress bar."""


@dataclass
class EvalResult:
    rows: list[dict[str, Any]]
    summary: dict[str, Any]
    out_dir: Path | None = None
    renders: dict[tuple[str, int], np.ndarray] = field(default_factory=dict)

    def mean(self, metric: str) -> float | str:
        return self.summary["mean"][metric]


# --- selection and validation ----------------------------------------------------------------------

def select_cameras(model: EvalModel, scene: EvalScene, names: Sequence[str]) -> list[int]:
    """Indices into ``scene.cameras`` to evaluate; checks they agree with the model's cameras."""
    scene_names = [c.name for c in scene.cameras]
    if names:
        unknown = [n for n in names if n not in scene_names]
        if unknown:
            raise EvalError(f"--cameras: {unknown} not in the scene (cameras: {', '.join(scene_names)})")
        indices = [scene_names.index(n) for n in dict.fromkeys(names)]
    else:
        indices = list(scene.test_indices)
        if not indices:
            where = getattr(scene, "root", None)  # a PreparedScene names its folder
            raise EvalError(f"{where if where is not None else 'the scene'}: no test cameras (none was held out); "
                            "name the cameras to evaluate with --cameras (their figures are training views)")
    model_cams = {c.name: c for c in model.cameras}
    for i in indices:
        sc = scene.cameras[i]
        mc = model_cams.get(sc.name)
        if mc is None:
            raise EvalError(f"camera {sc.name!r} of the scene is not one of the checkpoint's cameras "
                            f"({', '.join(model_cams)}); pass the --data the model was trained on")
        if not cameras_agree(mc, sc):
            raise EvalError(f"camera {sc.name!r} differs between the checkpoint and the scene (pose or "
                            "intrinsics); pass the --data the model was trained on")
    return indices


def cameras_agree(a: Camera, b: Camera, tol: float = 1e-4) -> bool:
    """Same pose, and same intrinsics up to an image rescale (K relative to the image size)."""
    scale = max(1.0, float(np.abs(a.w2c[:3, 3]).max()))
    if not np.allclose(a.w2c[:3, :3], b.w2c[:3, :3], atol=tol) or not np.allclose(a.t, b.t, atol=tol * scale):
        return False
    ka = a.K[:2] / np.array([[a.width], [a.height]])
    kb = b.K[:2] / np.array([[b.width], [b.height]])
    return bool(np.allclose(ka, kb, atol=tol))


def select_frames(model: EvalModel, scene: EvalScene, frames: Sequence[int], every: int) -> list[int]:
    if every < 1:
        raise EvalError(f"--every must be >= 1, got {every}")
    if int(model.num_frames) != int(scene.num_frames):
        raise EvalError(f"the checkpoint has {model.num_frames} frames but the scene has {scene.num_frames}; "
                        "pass the --data the model was trained on")
    n = int(scene.num_frames)
    chosen = sorted(dict.fromkeys(int(f) for f in frames)) if frames else list(range(n))
    bad = [f for f in chosen if not 0 <= f < n]
    if bad:
        raise EvalError(f"--frames: {bad} out of range [0, {n})")
    return chosen[::every]


def image_frames(frames: Sequence[int], count: int) -> set[int]:
    """``count`` evenly spaced entries of ``frames`` (first and last included)."""
    return {frames[p] for p in evenly_spaced(len(frames), count)}


# --- rendering and images --------------------------------------------------------------------------

def render_view(g: Gaussians, cam: Camera, background: "torch.Tensor | EnvironmentMap | None", backend: str,
                near: float = NEAR) -> torch.Tensor:
    """(H,W,3) render of ``g`` from ``cam`` culled at the model's ``near``, clamped to [0,1]."""
    return rasterize_gaussians(g, cam, background=background, backend=backend, near=near).image.detach().clamp(0.0, 1.0)


def comparison_image(render: np.ndarray, gt: np.ndarray, gain: float) -> np.ndarray:
    """render | ground truth | error heat map (black -> red -> yellow -> white), uint8."""
    err = np.clip(np.abs(render - gt).mean(-1) * gain, 0.0, 1.0)
    heat = np.stack([np.clip(3 * err, 0, 1), np.clip(3 * err - 1, 0, 1), np.clip(3 * err - 2, 0, 1)], -1)
    panel = np.concatenate([render, gt, heat], axis=1)
    return np.clip(np.round(panel * 255.0), 0, 255).astype(np.uint8)


# --- the evaluation --------------------------------------------------------------------------------

@dataclass
class Share:
    """An evaluation spread over several processes (the trainer's workers): this one scores the
    selected frames that are in ``frames``; ``gather(obj)`` returns every process's ``obj`` in rank
    order on the process that writes and None on the others
    (``atgs.train.distributed.Workers.gather_to_leader``)."""

    frames: Sequence[int]
    gather: Callable[[Any], list | None]


@dataclass
class _Scored:
    """One process's share of an evaluation: its views' rows and its frames' Gaussian counts."""

    rows: list[dict[str, Any]] = field(default_factory=list)
    gaussians: dict[int, int] = field(default_factory=dict)  # frame -> Gaussians drawn
    renders: dict[tuple[str, int], np.ndarray] = field(default_factory=dict)


def evaluate(model: EvalModel, scene: EvalScene, cfg: EvalConfig | None = None, out: Path | None = None,
             *, background: "Sequence[float] | torch.Tensor | EnvironmentMap | None" = None,
             settings: dict[str, Any] | None = None, keep_renders: bool = False,
             camera_transform: Callable[[int, torch.Tensor], torch.Tensor] | None = None,
             share: Share | None = None) -> EvalResult | None:
    """Evaluate ``model`` on ``scene`` (see the module docstring).

    ``background``: what the model was trained over, an RGB or an
    :class:`~atgs.render.environment.EnvironmentMap` (default ``model.environment``, else
    ``model.background``, else black). ``settings`` are extra entries for
    summary.json (e.g. checkpoint and data paths). ``keep_renders`` keeps the (H,W,3) renders in
    the result. ``camera_transform(camera index, render)``: what a camera did to the image before
    it is compared (the trainer's per-camera exposure when it evaluates a training camera); the
    result is clipped to [0, 1]. ``share``: spread over several processes, each scoring its
    frames; the one that gathers writes ``out`` and returns what one process would (the same rows
    in the same order, the same pictures), the others return None. Raises :class:`EvalError` on
    bad input.
    """
    cfg = cfg or EvalConfig()
    if background is None:  # the model's own: its environment map if it has one, else its colour
        background = getattr(model, "environment", None) or getattr(model, "background", None)
    if isinstance(background, EnvironmentMap):
        bg = background
    else:
        bg = None if background is None else torch.as_tensor(background, dtype=torch.float32, device="cpu").reshape(3)
    cam_indices = select_cameras(model, scene, cfg.cameras)
    frames = select_frames(model, scene, cfg.frames, cfg.every)
    if not 0.0 < cfg.resolution_scale <= 1.0:
        raise EvalError(f"--resolution-scale must be in (0, 1], got {cfg.resolution_scale}")
    if keep_renders and share is not None:
        raise ValueError("keep_renders: the renders of a shared evaluation stay with each process")
    if cfg.lpips:
        lpips_net, lpips_reason = load_lpips(cfg.lpips_backbone, cfg.lpips_linear)
    else:
        lpips_net, lpips_reason = None, "disabled (--no-lpips)"
    cams = _eval_cameras(scene, cam_indices, cfg.resolution_scale)
    small = [c.name for c in cams if min(c.width, c.height) < LPIPS.MIN_SIZE]
    if lpips_net is not None and small:
        lpips_net, lpips_reason = None, f"images of {', '.join(small)} are smaller than {LPIPS.MIN_SIZE} px"
    if out is not None:
        out = Path(out)
        if out.exists() and not out.is_dir():
            raise EvalError(f"--out {out}: exists and is not a directory; choose another --out")
    pictured = image_frames(frames, cfg.images_per_camera) if out is not None else set()
    t0 = time.perf_counter()

    def score(own: list[int], picture: Callable[[str, int, np.ndarray], None]) -> _Scored:
        return _score(model, scene, cfg, cam_indices, cams, own, lpips_net, bg, keep_renders, camera_transform,
                      pictured, picture)

    def finish(scored: _Scored, tmp: Path | None) -> EvalResult:
        exposure_fit = add_matched_psnr(scored.rows)  # needs every frame of a camera: after gathering
        summary = _summary(scored.rows, cams, frames, cfg, lpips_net is not None, lpips_reason,
                           [scored.gaussians[f] for f in frames if f in scored.gaussians],
                           time.perf_counter() - t0, bg, settings or {})
        summary["exposure_fit"] = exposure_fit
        if tmp is not None:
            write_csv(tmp / "per_view.csv", scored.rows)
            (tmp / "summary.json").write_text(json.dumps(json_safe(summary), indent=1) + "\n")
        return EvalResult(rows=scored.rows, summary=summary, renders=scored.renders)

    if share is not None:
        return _shared(share, frames, cam_indices, scene, out, score, finish)
    if out is None:
        return finish(score(frames, _no_picture), None)
    with atomic_dir(out, overwrite=True) as tmp:
        result = finish(score(frames, _picture_writer(tmp)), tmp)
    result.out_dir = out
    return result


def _no_picture(camera: str, frame: int, image: np.ndarray) -> None:
    raise AssertionError("no pictures without an output directory")


def _picture_writer(root: Path) -> Callable[[str, int, np.ndarray], None]:
    def write(camera: str, frame: int, image: np.ndarray) -> None:
        d = root / "images" / camera
        d.mkdir(parents=True, exist_ok=True)
        Image.fromarray(image).save(d / f"{frame:06d}.png", compress_level=1)
    return write


def _shared(share: Share, frames: list[int], cam_indices: list[int], scene: EvalScene, out: Path | None,
            score: Callable, finish: Callable) -> EvalResult | None:
    """Each process scores its frames (and encodes its pictures); the writer merges them in one
    process's order (frames, then cameras) and writes ``out``."""
    own = set(int(f) for f in share.frames)
    pictures: dict[tuple[str, int], bytes] = {}

    def keep(camera: str, frame: int, image: np.ndarray) -> None:
        buf = io.BytesIO()
        Image.fromarray(image).save(buf, format="png", compress_level=1)
        pictures[(camera, frame)] = buf.getvalue()

    mine = score([f for f in frames if f in own], keep)
    parts = share.gather((mine.rows, mine.gaussians, pictures))
    if parts is None:
        return None
    frame_at = {f: k for k, f in enumerate(frames)}
    camera_at = {scene.cameras[i].name: k for k, i in enumerate(cam_indices)}
    merged = _Scored(rows=sorted((r for rows, _, _ in parts for r in rows),
                                 key=lambda r: (frame_at[r["frame"]], camera_at[r["camera"]])),
                     gaussians={f: n for _, counts, _ in parts for f, n in counts.items()})
    scored_frames = [r["frame"] for r in merged.rows]
    if sorted(set(scored_frames)) != frames or len(merged.rows) != len(frames) * len(cam_indices):
        raise AssertionError("the processes' frames do not cover the evaluation exactly once")
    if out is None:
        return finish(merged, None)
    with atomic_dir(out, overwrite=True) as tmp:
        for _, _, pngs in parts:
            for (camera, frame), png in pngs.items():
                d = tmp / "images" / camera
                d.mkdir(parents=True, exist_ok=True)
                (d / f"{frame:06d}.png").write_bytes(png)
        result = finish(merged, tmp)
    result.out_dir = out
    return result


def _score(model: EvalModel, scene: EvalScene, cfg: EvalConfig, cam_indices: list[int], cams: list[Camera],
           frames: list[int], lpips_net: Any, background: torch.Tensor | EnvironmentMap | None,
           keep_renders: bool, camera_transform: Callable[[int, torch.Tensor], torch.Tensor] | None,
           pictured: set[int], picture: Callable[[str, int, np.ndarray], None]) -> _Scored:
    """Render and score ``frames`` x cameras; the comparison image of each view at a ``pictured``
    frame goes to ``picture``."""
    scored = _Scored()
    near = near_of(model)  # the plane training rendered with, for every camera held out or not
    was_training = getattr(model, "training", None)
    if was_training and hasattr(model, "train"):
        model.train(False)
    try:
        with torch.no_grad(), progress_bar(len(frames) * len(cams), "evaluate", unit="view",
                                           enabled=cfg.progress) as bar:
            for f in frames:
                g = model.gaussians_at_frame(f).detach()
                scored.gaussians[f] = len(g)
                for ci, cam in zip(cam_indices, cams):
                    gt_np = _ground_truth(scene, ci, f, cam)  # checked against the scene, resized to cam
                    bg = background
                    if isinstance(bg, torch.Tensor):
                        bg = bg.to(g.means.device, g.means.dtype)
                    render = render_view(g, cam, bg, cfg.backend, near)  # on the model's device
                    if camera_transform is not None:
                        render = camera_transform(ci, render).clamp(0, 1)
                    gt = torch.from_numpy(gt_np).to(render.device, render.dtype)
                    row: dict[str, Any] = {"camera": cam.name, "frame": f, **all_metrics(render, gt)}
                    row["_exposure_sums"] = view_sums(render, gt)  # psnr_matched, once the camera is fitted
                    row["lpips"] = UNAVAILABLE if lpips_net is None else float(lpips_net(render.cpu(), gt.cpu()))
                    scored.rows.append(row)
                    render_np = render.cpu().numpy().astype(np.float32)
                    if keep_renders:
                        scored.renders[(cam.name, f)] = render_np
                    if f in pictured:
                        picture(cam.name, f, comparison_image(render_np, gt_np, cfg.error_gain))
                    bar.update(1)
                    bar.set_postfix(cam=cam.name, frame=f, psnr=f"{row['psnr']:.2f}")
    finally:
        if was_training and hasattr(model, "train"):
            model.train(True)
    return scored


def _eval_cameras(scene: EvalScene, cam_indices: list[int], scale: float) -> list[Camera]:
    return [scene.cameras[i].scaled(scale) if scale != 1.0 else scene.cameras[i] for i in cam_indices]


def _ground_truth(scene: EvalScene, ci: int, f: int, cam: Camera) -> np.ndarray:
    """Ground truth of camera ``ci`` at frame ``f`` as float32 (H,W,3), at ``cam``'s size."""
    full = scene.cameras[ci]
    try:
        img = np.asarray(scene.image(ci, f), dtype=np.float32)
    except UserError as e:  # already one line naming the file
        raise EvalError(str(e)) from None
    except (OSError, IndexError) as e:
        raise EvalError(f"ground truth of camera {cam.name!r} frame {f}: {e}") from None
    if img.shape != (full.height, full.width, 3):
        raise EvalError(f"ground truth of camera {cam.name!r} frame {f} has shape {img.shape}, "
                        f"expected ({full.height}, {full.width}, 3)")
    if (cam.width, cam.height) != (full.width, full.height):  # as the trainer sees it (uint8, Lanczos)
        u8 = np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)
        img = resize_frame(u8, cam.width, cam.height).astype(np.float32) / 255.0
    return img


def _mean(rows: list[dict[str, Any]], metric: str) -> float | str:
    vals = [r[metric] for r in rows]
    if not vals or any(isinstance(v, str) for v in vals):
        return UNAVAILABLE
    return float(np.mean(vals))  # PSNR: mean of per-view PSNR (inf if any view is exact)


def _summary(rows: list[dict[str, Any]], cams: list[Camera], frames: list[int], cfg: EvalConfig,
             lpips_ok: bool, lpips_reason: str, num_gaussians: list[int], elapsed: float,
             background: torch.Tensor | None, settings: dict[str, Any]) -> dict[str, Any]:
    h, w = (cams[0].height, cams[0].width) if cams else (0, 0)
    return {
        "format": "atgs-eval",
        "version": 1,
        "num_views": len(rows),
        "mean": {m: _mean(rows, m) for m in METRICS},
        "per_camera": {c.name: {m: _mean([r for r in rows if r["camera"] == c.name], m) for m in METRICS}
                       for c in cams},
        "lpips": {"available": lpips_ok, "reason": "" if lpips_ok else lpips_reason},
        "settings": {
            **settings,
            "cameras": [c.name for c in cams],
            "frames": frames,
            "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(cfg).items()},
            "background": (None if background is None else "environment map, mean "
                           + str([round(v, 4) for v in background.mean_colour()])
                           if isinstance(background, EnvironmentMap) else [float(v) for v in background]),
            "image_sizes": sorted({f"{c.width}x{c.height}" for c in cams}),
            "ms_ssim_levels": ms_ssim_levels(h, w) if cams else None,
            "mean_gaussians": float(np.mean(num_gaussians)) if num_gaussians else 0.0,
            "seconds": round(elapsed, 3),
        },
        "definitions": METRIC_DEFINITIONS,
    }


# --- output files ----------------------------------------------------------------------------------

def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return "inf" if math.isinf(v) and v > 0 else ("nan" if math.isnan(v) else f"{v:.6f}")
    return str(v)


def write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["camera", "frame", *METRICS])
        for r in rows:
            w.writerow([r["camera"], r["frame"], *(_fmt(r[m]) for m in METRICS)])


def json_safe(obj: Any) -> Any:
    """Strict JSON: non-finite floats become the strings "inf", "-inf", "nan"."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return "nan" if math.isnan(obj) else ("inf" if obj > 0 else "-inf")
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    return obj
