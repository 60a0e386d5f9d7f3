"""Decode ATGS frames in OpenGL compute shaders, straight into the splat shader's vertex columns.

Why (docs/viewer.md, "Decoding on the GPU without a host round trip"): on an NVIDIA H200 the torch
decode of a trained built-in model took 5-10 ms a frame of which the GPU was busy 2 ms: about 150
kernel launches, then the packed columns copied to host memory and uploaded to the GL again. Here
a frame is one compute dispatch over the keyframe window's anchors (atgs/shaders/decode.comp)
that writes the columns the splat shader reads, in GL buffers: no launches per layer, nothing
through host memory, and any GPU with OpenGL 4.3 decodes (Intel, AMD, NVIDIA without CUDA).

What is uploaded, once per model: per anchor its time-invariant values (:data:`ANCHOR_FIELDS`, then
``f_a + f_s``), the 4D hash table, the temporal MLPs, the decoder heads and the clearance
centres. Per keyframe window: the window's anchor ids. Per frame: a few uniforms (the frame, the
segment, each level's time vertex and weights). Everything else is the shader's.

The torch decode (``ATGSModel.gaussians_at_frame``) is the reference: tests/test_viewer_gl_decode.py
compares the two on llvmpipe. Differences are float32 summation order, and the Gaussians the torch
decode drops (faded out, cut, inside a camera, not finite) are here slots of opacity 0, which the
sort and the splat shader cull, so the image is the same.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal

import moderngl
import numpy as np
import torch

from atgs.model.anchor_motion import MIN_FADE_WIDTH, max_fade_width
from atgs.model.atgs_model import ATGSModel
from atgs.model.decoder import GaussianDecoder
from atgs.model.fast_decode import plain_heads
from atgs.shaders import load_shader
from atgs.viewer.errors import ViewerError

DecodeRoute = Literal["torch", "gl"]
"""Where the player decodes frames: torch (on --device, then uploaded) or GL compute shaders."""

MIN_GL = 430  # compute shaders and storage buffers
STORAGE_BLOCKS = 8  # the shader binds eight storage buffers (the minimum GL 4.3 guarantees)
LOCAL_SIZE = 64
ANCHOR_FIELDS = ("mu x3", "normalized position x3", "exp(v[:3]) x3", "exp(v[3:]) x3", "velocity x3",
                 "keyframe frame", "fade width", "smoothing variance", "inside the grid box", "static")
ANCHOR_STRIDE = 20


class GLDecodeUnavailable(RuntimeError):
    """The GL or the model cannot take the compute-shader decode (the message says why)."""


def gl_decode_problem(ctx: moderngl.Context, model: object) -> str | None:
    """Why the compute-shader decode cannot serve ``model`` on ``ctx``, or None when it can."""
    if not isinstance(model, ATGSModel):
        return "only ATGS checkpoints decode on the GL (PLY files and the demo are not decoded)"
    if ctx.version_code < MIN_GL:
        return f"OpenGL {ctx.version_code // 100}.{ctx.version_code % 100 // 10} has no compute shaders (4.3 needed)"
    blocks = ctx.info.get("GL_MAX_COMPUTE_SHADER_STORAGE_BLOCKS", STORAGE_BLOCKS)
    if blocks < STORAGE_BLOCKS:
        return f"the GL allows {blocks} storage buffers in a compute shader, the decode binds {STORAGE_BLOCKS}"
    if plain_heads(model.decoder) is None:
        return "the decoder is not the plain float32 MLPs (e.g. a reduced-precision view)"
    return None


def gl_decoder_for(ctx: moderngl.Context, source: object) -> "GLFrameDecoder":
    """``--decode gl``'s decoder of ``source``, or a one-line ViewerError saying why it cannot be."""
    try:
        return GLFrameDecoder(ctx, source)  # type: ignore[arg-type]
    except GLDecodeUnavailable as e:
        raise ViewerError(f"--decode gl: {e}; use --decode torch") from None


@dataclass
class GLFrame:
    """A decoded frame living in GL buffers: ``count`` Gaussians in the packing layout."""

    frame: int
    count: int  # slots: the window's anchors x q (the torch decode's dropped Gaussians have opacity 0)
    num_anchors: int
    columns: tuple[moderngl.Buffer, ...]  # mean, quat, scale, opacity_rgb (viewer.packing.COLUMNS)
    decode_ms: float = 0.0  # host time to issue the decode (the GL runs it later)


def _f32(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to("cpu", torch.float32).numpy())


class GLFrameDecoder:
    """Decodes frames of one :class:`ATGSModel` on the GL of ``ctx`` (use from its thread).

    ``decode(f)`` returns a :class:`GLFrame` whose buffers belong to one of ``slots`` sets that
    are used in turn, so a frame being drawn is never overwritten by the next one's decode
    (2: decode t+1 while t is drawn)."""

    def __init__(self, ctx: moderngl.Context, model: ATGSModel, slots: int = 2,
                 block_bytes: int | None = None) -> None:
        """``block_bytes``: the largest storage buffer the shader may bind (default: the GL's
        GL_MAX_SHADER_STORAGE_BLOCK_SIZE); a hash table larger than it is kept one segment's grid
        at a time."""
        problem = gl_decode_problem(ctx, model)
        if problem:
            raise GLDecodeUnavailable(problem)
        self.ctx, self.model = ctx, model
        cfg, hg = model.cfg, model.hash
        self.q = int(cfg.gaussians_per_anchor)
        weights, offsets = self._weight_array(model)
        max_block = int(block_bytes or ctx.info.get("GL_MAX_SHADER_STORAGE_BLOCK_SIZE", 1 << 27))
        anchors = self._anchor_rows(model)
        for what, nbytes in (("anchor table", anchors.nbytes), ("MLP weights", weights.nbytes),
                             ("hash grid of one segment", 4 * hg.levels * hg.table_size * hg.features)):
            if nbytes > max_block:
                raise GLDecodeUnavailable(f"the model's {what} needs {nbytes / 2**20:.0f} MiB in one storage buffer, "
                                          f"the GL allows {max_block / 2**20:.0f} MiB")
        per_grid = hg.levels * hg.table_size
        table = _f32(hg.table)
        # the whole table when the GL takes it in one block, else the current segment's grid
        self._one_grid_at_a_time = table.nbytes > max_block
        self._table_grid = -1
        self._table_np = table
        defines = {
            "LEVELS": hg.levels, "FEATS": hg.features, "TABLE_SIZE": hg.table_size,
            "RES_LIST": ", ".join(str(r) for r in hg.res),
            "TIME_RES_LIST": ", ".join(str(r) for r in hg.time_res),
            "DENSE_LIST": ", ".join(str(int(hg.dense_level(lv))) for lv in range(hg.levels)),
            "D": cfg.feature_dim, "TMLP_IN": hg.levels * hg.features, "TMLP_HIDDEN": model.tmlp_w1.shape[2],
            "Q": self.q, "ANCHOR_STRIDE": ANCHOR_STRIDE, "FADE": int(bool(cfg.temporal_fade)),
            "NUM_CENTRES": model.clearance.centres.shape[0] if model.clearance.active else 0,
            **{f"H_{n.upper()}": getattr(cfg, f"hidden_{n}") for n in GaussianDecoder.HEADS},
            **offsets,
        }
        self.program = ctx.compute_shader(load_shader("decode.comp", defines))
        self._anchors = ctx.buffer(anchors.tobytes())
        self._table = ctx.buffer(table.tobytes() if not self._one_grid_at_a_time
                                 else table[:per_grid].tobytes())
        self._weights = ctx.buffer(weights.tobytes())
        self._active: moderngl.Buffer | None = None
        self._window: tuple | None = None
        self._count = 0
        self._slots: list[list[moderngl.Buffer | None]] = [[None] * 4 for _ in range(max(1, slots))]
        self._next_slot = 0
        self._fade_cut = model.fade_cut()

    # --- what is uploaded once ----------------------------------------------------------------
    @staticmethod
    def _anchor_rows(model: ATGSModel) -> np.ndarray:
        """(N, ANCHOR_STRIDE + D) float32: ANCHOR_FIELDS, then f_a + f_s."""
        with torch.no_grad():
            mu = model.anchor_mu.float()
            n = mu.shape[0]
            xn = model.normalized_positions(mu)
            inside = ((xn >= 0) & (xn <= 1)).all(1, keepdim=True).float()
            fa = model.anchor_feature
            if model.cfg.use_spatial_grid:
                fa = fa + model.spatial.query(xn, False)[0]
            ls = model.anchor_log_scale
            velocity = model.anchor_velocity if model.cfg.anchor_velocity else torch.zeros_like(mu)
            tl = model.timeline
            kf = model.anchor_keyframe
            frames = torch.tensor(tl.keyframe_frames(), dtype=torch.float32, device=mu.device)
            kf_frame = frames[kf.clamp_min(0)]
            static = (kf < 0) | (tl.num_keyframes <= 1) | (tl.num_frames <= 1)
            width = torch.exp(model.anchor_fade[:, 0]).clamp(min=MIN_FADE_WIDTH, max=max_fade_width(tl))
            var = model.smoothing_variance()
            var = torch.zeros(n, device=mu.device) if var is None else var
            rows = torch.cat([mu, xn, torch.exp(ls[:, :3]), torch.exp(ls[:, 3:]), velocity, kf_frame[:, None],
                              width[:, None], var[:, None], inside, static.float()[:, None], fa], dim=1)
        assert rows.shape[1] == ANCHOR_STRIDE + model.cfg.feature_dim
        return _f32(rows)

    @staticmethod
    def _weight_array(model: ATGSModel) -> tuple[np.ndarray, dict[str, int]]:
        """Every MLP weight and the clearance centres in one float32 array, and the #defines of
        their offsets (the shader indexes it: temporal MLPs as stored, the heads' first layers
        row by hidden unit, their second layers transposed)."""
        parts, offsets, at = [], {}, 0

        def put(name: str, t: torch.Tensor) -> None:
            nonlocal at
            a = _f32(t).reshape(-1)
            offsets[name] = at
            parts.append(a)
            at += a.size

        for name, t in (("OFF_TW1", model.tmlp_w1), ("OFF_TB1", model.tmlp_b1), ("OFF_TW2", model.tmlp_w2),
                        ("OFF_TB2", model.tmlp_b2)):
            put(name, t)
        for head_name, (first, second) in zip(GaussianDecoder.HEADS, plain_heads(model.decoder)):
            key = head_name.upper()
            put(f"OFF_{key}_W1", first.weight)
            put(f"OFF_{key}_B1", first.bias)
            put(f"OFF_{key}_W2T", second.weight.T)
            put(f"OFF_{key}_B2", second.bias)
        put("OFF_CENTRES", model.clearance.centres if model.clearance.active else torch.zeros(1))
        return np.concatenate(parts).astype(np.float32), offsets

    # --- per window and per frame -------------------------------------------------------------
    def _set_window(self, f: int) -> None:
        m = self.model
        key = (m.timeline.window_of_frame(f), bool(m.cfg.static_keyframe0), m.cfg.anchor_layout)
        if key == self._window:
            return
        ids = m.active_anchors(f).nonzero().squeeze(1).to("cpu", torch.int64).numpy().astype(np.uint32)
        self._count = int(ids.size)
        if self._active is None or self._active.size < max(4, ids.nbytes):
            if self._active is not None:
                self._active.release()
            self._active = self.ctx.buffer(reserve=max(4096, 2 * ids.nbytes))
        if ids.size:
            self._active.write(ids.tobytes())
        self._window = key

    def _set_grid(self, grid: int) -> int:
        """The table row where grid ``grid`` starts in the GL's table buffer."""
        per_grid = self.model.hash.levels * self.model.hash.table_size
        if not self._one_grid_at_a_time:
            return grid * per_grid
        if grid != self._table_grid:
            self._table.write(self._table_np[grid * per_grid:(grid + 1) * per_grid].tobytes())
            self._table_grid = grid
        return 0

    def _outputs(self, count: int) -> tuple[moderngl.Buffer, ...]:
        slot = self._slots[self._next_slot]
        self._next_slot = (self._next_slot + 1) % len(self._slots)
        for i, per in enumerate((12, 8, 12, 8)):
            need = max(4, count * per)
            if slot[i] is None or slot[i].size < need:
                if slot[i] is not None:
                    slot[i].release()
                slot[i] = self.ctx.buffer(reserve=1 << max(12, (need - 1).bit_length()))
        return tuple(slot)  # type: ignore[arg-type]

    def decode(self, f: int) -> GLFrame:
        """Issue frame f's decode (no wait: the GL runs it before anything that reads the columns)."""
        t0 = time.perf_counter()
        m = self.model
        tl = m.timeline
        f = int(f)
        self._set_window(f)
        grid = tl.segment_of_frame(f) - m.first_segment
        tau = tl.local_time_of_frame(f)
        hg = m.hash
        corners = [hg.time_corners(tau, lv) for lv in range(hg.levels)]
        count = self._count * self.q
        out = self._outputs(count)
        if self._count:
            p = self.program
            K, F = tl.num_keyframes, tl.num_frames
            uniforms = {
                "u_count": self._count, "u_table_base": self._set_grid(grid), "u_frame": float(f),
                "u_kf_factor": (K - 1) / (F - 1) if K > 1 and F > 1 else 0.0, "u_grid": grid,
                "u_fade_cut": self._fade_cut, "u_opacity_cut": float(m.cfg.opacity_threshold),
                "u_cut_on": int(m.cfg.opacity_threshold > 0),
                "u_clear_r2": float(m.clearance.radius) ** 2 if m.clearance.active else 0.0,
            }
            for name, value in uniforms.items():
                member = p.get(name, None)
                if member is not None:
                    member.value = value
            for name, values in (("u_v0", [c[0] for c in corners]), ("u_tw0", [c[1] for c in corners]),
                                 ("u_tw1", [c[2] for c in corners])):
                member = p.get(name, None)
                if member is not None:
                    member.value = values if hg.levels > 1 else values[0]
            for binding, buf in enumerate((self._anchors, self._table, self._weights, self._active, *out)):
                buf.bind_to_storage_buffer(binding)
            p.run(-(-self._count // LOCAL_SIZE))
            # the splat draw reads the columns as vertex attributes, the GL sort as storage
            self.ctx.memory_barrier(moderngl.VERTEX_ATTRIB_ARRAY_BARRIER_BIT | moderngl.SHADER_STORAGE_BARRIER_BIT)
        return GLFrame(f, count, self._count, out, (time.perf_counter() - t0) * 1e3)

    def release(self) -> None:
        for obj in (self.program, self._anchors, self._table, self._weights, self._active,
                    *(b for slot in self._slots for b in slot)):
            if obj is not None:
                obj.release()


class GLFrameFeeder:
    """The player's frames when they are decoded on the GL (the counterpart of
    :class:`viewer.playback.FrameFeeder`): the shown frame is decoded when the playhead reaches it,
    unless :meth:`after_draw` decoded it already while the previous one was drawn (frame t+1 is
    issued right after t's draw, into the other buffer set, so the GL runs it behind that draw and
    the UI never waits for it)."""

    def __init__(self, decoder: GLFrameDecoder) -> None:
        self.decoder = decoder
        self.shown: GLFrame | None = None
        self._ahead: GLFrame | None = None

    def update(self, playback) -> tuple[GLFrame, bool]:
        """(frame to show, whether it changed since the last call)."""
        f = playback.frame
        if self.shown is not None and self.shown.frame == f:
            return self.shown, False
        ahead, self._ahead = self._ahead, None
        self.shown = ahead if ahead is not None and ahead.frame == f else self.decoder.decode(f)
        return self.shown, True

    def after_draw(self, playback) -> None:
        """While playing, decode the next frame now (behind the draw just issued)."""
        if not playback.playing:
            return
        upcoming = playback.upcoming(2)
        if len(upcoming) > 1 and (self._ahead is None or self._ahead.frame != upcoming[1]):
            self._ahead = self.decoder.decode(upcoming[1])

    def close(self) -> None:
        self.decoder.release()
