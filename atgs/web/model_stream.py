"""The model itself as a web stream (``atgs-export --format web --web-stream model``, docs/web.md,
"Streaming the model"): the page decodes ATGS on the viewer's GPU (atgs/web/player/model_decode.js)
instead of downloading every frame's Gaussians.

The stream folder holds manifest.json (``kind: "model"``: the decode's sizes, the timeline's
per-frame values and the part files) and part files (:mod:`atgs.web.model_format`):

- ``weights.bin``: the segments' temporal MLPs, the four decoder heads, the clearance centres,
  always float32 (a few hundred KB at most);
- ``anchors_static.bin`` and ``anchors_kf_NNNN.bin``: the static anchors and each keyframe's
  (of the exported frames' windows), each anchor's position, log scales, velocity, log fade width and ``f_a + f_s`` (the spatial
  grid F_s is time-invariant, so its lookup at each anchor is done here and the grid is not
  shipped), and its 3D smoothing variance when the model filters;
- ``hash_seg_NNNN.bin``: one time segment's 4D hash grid (of the exported frames' segments).

Frame f needs the weights, the anchors of its keyframe window (ATGSModel.active_anchors) and its
segment's hash grid: the manifest lists the part files of each frame, and the page fetches them as
the playhead nears. The big tensors (anchors, hash grids) are stored at ``precision``: float32,
float16, or int8 with a scale per column (per hash level and feature); positions at float16 and
int8 are 16-bit over the anchors' box. :func:`read_model_stream` is the plain reference reader.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from atgs.model.anchor_motion import MIN_FADE_WIDTH, max_fade_width
from atgs.model.anchors import STATIC
from atgs.model.decoder import GaussianDecoder
from atgs.model.fast_decode import plain_heads
from atgs.web.model_format import PRECISIONS, Encoded, encode, pack_part, read_part

KIND = "model"
WEIGHTS_FILE = "weights.bin"
# which stored dtype each precision gives the anchors' positions and the other big tensors
POSITION_DTYPE = {"float32": "f32", "float16": "u16", "int8": "u16"}
TENSOR_DTYPE = {"float32": "f32", "float16": "f16", "int8": "i8"}


class ModelStreamUnavailable(ValueError):
    """The model cannot be streamed as a model (the message says why)."""


def anchor_file(keyframe: int) -> str:
    return "anchors_static.bin" if keyframe == STATIC else f"anchors_kf_{keyframe:04d}.bin"


def hash_file(segment: int) -> str:
    return f"hash_seg_{segment:04d}.bin"


def anchor_groups(model) -> list[tuple[int, torch.Tensor]]:
    """(keyframe, ascending anchor ids) of each anchor part, static first then by keyframe: the
    order the page lays out a frame's anchors in (its Gaussian slot a q + j is anchor a's j-th)."""
    kf = model.anchor_keyframe.cpu()
    return [(int(k), (kf == k).nonzero().squeeze(1)) for k in torch.unique(kf).tolist()]


def check_streamable(model) -> None:
    if not hasattr(model, "anchor_mu"):
        raise ModelStreamUnavailable("--web-stream model needs an ATGS checkpoint")
    if plain_heads(model.decoder) is None:
        raise ModelStreamUnavailable("--web-stream model needs the plain float32 decoder heads")
    if model.first_segment != 0 or model.hash.num_grids != model.num_segments:
        raise ModelStreamUnavailable("--web-stream model needs every segment's hash grid (a whole model)")


def _weights_part(model) -> list[Encoded]:
    out = [encode(n, getattr(model, n).detach().cpu().numpy(), "f32")
           for n in ("tmlp_w1", "tmlp_b1", "tmlp_w2", "tmlp_b2")]
    for name, (first, second) in zip(GaussianDecoder.HEADS, plain_heads(model.decoder)):
        for key, t in (("w1", first.weight), ("b1", first.bias), ("w2", second.weight), ("b2", second.bias)):
            out.append(encode(f"{name}.{key}", t.detach().cpu().numpy(), "f32"))
    if model.clearance.active:
        out.append(encode("centres", model.clearance.centres.cpu().numpy(), "f32"))
    return out


def anchor_tensors(model, ids: torch.Tensor) -> dict[str, np.ndarray]:
    """The per-anchor tensors a part ships for anchors ``ids`` (float32, before storage)."""
    with torch.no_grad():
        mu = model.anchor_mu.cpu()[ids]
        fa = model.anchor_feature.cpu()[ids]
        if model.cfg.use_spatial_grid:
            fa = fa + model.spatial.query(model.normalized_positions(mu), False)[0]
        out = {"mu": mu, "log_scale": model.anchor_log_scale.cpu()[ids], "feature": fa}
        if model.cfg.anchor_velocity:
            out["velocity"] = model.anchor_velocity.cpu()[ids]
        if model.cfg.temporal_fade:
            out["fade"] = model.anchor_fade.cpu()[ids]
        var = model.smoothing_variance()
        if var is not None:
            out["smoothing"] = var.cpu()[ids]
    return {k: v.float().numpy() for k, v in out.items()}


def _anchor_part(model, ids: torch.Tensor, precision: str) -> list[Encoded]:
    tensors = anchor_tensors(model, ids)
    return [encode(name, x, POSITION_DTYPE[precision] if name == "mu" else TENSOR_DTYPE[precision])
            for name, x in tensors.items()]


def _hash_part(model, segment: int, precision: str) -> list[Encoded]:
    hg = model.hash
    per = hg.levels * hg.table_size
    rows = hg.table[segment * per:(segment + 1) * per].detach().cpu().numpy()
    return [encode("hash", rows, TENSOR_DTYPE[precision], groups=hg.levels)]


def decode_sizes(model) -> dict:
    """What the page's shaders are compiled for and the per-anchor rules' constants."""
    cfg, hg, tl = model.cfg, model.hash, model.timeline
    K, F = tl.num_keyframes, tl.num_frames
    width = max_fade_width(tl)
    return {
        "q": int(cfg.gaussians_per_anchor), "feature_dim": int(cfg.feature_dim),
        "hash": {"levels": hg.levels, "features": hg.features, "table_size": hg.table_size, "res": list(hg.res),
                 "dense": [bool(hg.dense_level(lv)) for lv in range(hg.levels)]},
        "tmlp_hidden": int(model.tmlp_w1.shape[2]),
        "heads": {n: int(getattr(cfg, f"hidden_{n}")) for n in GaussianDecoder.HEADS},
        "bbox_min": model.bbox_min.cpu().tolist(), "bbox_max": model.bbox_max.cpu().tolist(),
        "keyframe_frames": tl.keyframe_frames(),
        "kf_factor": (K - 1) / (F - 1) if K > 1 and F > 1 else 0.0,
        "temporal_fade": bool(cfg.temporal_fade), "anchor_velocity": bool(cfg.anchor_velocity),
        "smoothing": model.smoothing_variance() is not None,
        "fade_width": [MIN_FADE_WIDTH, None if math.isinf(width) else width],  # clamp (None: no cap)
        "fade_cut": model.fade_cut(), "opacity_threshold": float(cfg.opacity_threshold),
        "clearance_radius": float(model.clearance.radius) if model.clearance.active else 0.0,
    }  # fmt: skip


def frame_entry(model, f: int, part_of_keyframe: dict[int, int], part_of_segment: dict[int, int]) -> dict:
    """Frame f's values: the part files it needs (weights, its window's anchors in page order,
    its segment's grid) and its hash time corners per level (as the torch decode computes them)."""
    tl, hg = model.timeline, model.hash
    m, tau = tl.segment_of_frame(f), tl.local_time_of_frame(f)
    active = model.active_anchors(f).cpu()
    kf = model.anchor_keyframe.cpu()
    anchors = [part_of_keyframe[k] for k in part_of_keyframe if bool(active[kf == k].any())]
    return {"frame": int(f), "segment": m, "anchors": anchors, "hash": part_of_segment[m],
            "corners": [list(hg.time_corners(tau, lv)) for lv in range(hg.levels)]}


@dataclass
class PartInfo:
    file: str
    kind: str  # weights, anchors, hash
    bytes: int
    values: int  # the tensors' values: the page holds a part as float32, 4 bytes each (its byte budget)
    anchors: int = 0
    keyframe: int | None = None  # anchors: STATIC (-1) or the keyframe
    segment: int | None = None  # hash


def write_model_stream(model, folder: Path, frames: list[int], precision: str = "float16") -> tuple[dict, list[PartInfo]]:
    """Write the part files into ``folder``; returns (the manifest's ``model`` entry, the parts)."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    check_streamable(model)
    parts: list[PartInfo] = []

    def put(name: str, kind: str, tensors: list[Encoded], **info) -> int:
        data = pack_part(tensors)
        (folder / name).write_bytes(data)
        parts.append(PartInfo(name, kind, len(data), sum(math.prod(t.shape) for t in tensors), **info))
        return len(parts) - 1

    put(WEIGHTS_FILE, "weights", _weights_part(model))
    shown = torch.zeros(model.num_anchors, dtype=torch.bool)
    for f in frames:
        shown |= model.active_anchors(f).cpu()
    # the anchors of the exported frames' windows only (an export of a few frames ships their keyframes)
    part_of_keyframe = {k: put(anchor_file(k), "anchors", _anchor_part(model, ids, precision), anchors=int(ids.numel()),
                               keyframe=k) for k, ids in anchor_groups(model) if bool(shown[ids].any())}
    needed = sorted({model.timeline.segment_of_frame(f) for f in frames})
    part_of_segment = {m: put(hash_file(m), "hash", _hash_part(model, m, precision), segment=m) for m in needed}
    entry = {"precision": precision, **decode_sizes(model), "weights": 0,
             "parts": [dict(vars(p)) for p in parts],
             "frames": [frame_entry(model, f, part_of_keyframe, part_of_segment) for f in frames]}
    return entry, parts


@dataclass
class ModelStreamFiles:
    """A model stream read back (the reference reader): its manifest and every part's tensors."""

    manifest: dict
    parts: list[dict[str, np.ndarray]]  # in the order of the manifest's model.parts


def read_model_stream(stream: Path) -> ModelStreamFiles:
    """The manifest and the dequantized tensors of every part of a model stream folder."""
    manifest = json.loads((Path(stream) / "manifest.json").read_text())
    if manifest.get("kind") != KIND:
        raise ValueError(f"{stream}: not a model stream (kind {manifest.get('kind')!r})")
    parts = [read_part((Path(stream) / p["file"]).read_bytes(), p["file"]) for p in manifest["model"]["parts"]]
    return ModelStreamFiles(manifest, parts)
