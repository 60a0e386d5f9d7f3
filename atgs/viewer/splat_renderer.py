"""GLSL Gaussian splatting with the training rasterizer's conventions (moderngl, GL 3.3 core).

One triangle per Gaussian from a single indexed draw of points: the element buffer lists the
Gaussians in back-to-front order (a radix sort of quantized view depths on the device the
decoded Gaussians live on, redone only when the camera or the Gaussians change; a camera move
uploads only this buffer), the vertex shader builds each Gaussian's covariance from its
rotation and scale and projects it once, and a geometry shader emits its triangle. The
Gaussians themselves are the compact vertex columns of :mod:`viewer.packing`, uploaded once
per video frame (plus an optional column of spherical-harmonic coefficients, drawn by a shader
variant per SH degree). Blending is premultiplied back to front, ``(ONE, ONE_MINUS_SRC_ALPHA)``,
into a float target cleared to the background, which yields ``C + T bg`` and ``alpha = 1 - T``
like :func:`atgs.render.rasterize`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal, get_args

import moderngl
import numpy as np

from atgs.cameras import Camera
from atgs.shaders import load_shader
from atgs.viewer.packing import COLUMN_FORMATS, COLUMNS, PackedGaussians
from atgs.viewer.sorting import FrustumCull, back_to_front, view_depths

RenderMode = Literal["color", "depth", "alpha"]
MODES: tuple[str, ...] = get_args(RenderMode)

# Same numbers as atgs.render.constants (kept literal here so the viewer imports no torch code
# path it does not need; tests check they agree). NEAR is the default near plane only: a model
# is drawn with its own (``SplatRenderer(near=...)``, atgs.model.near_plane).
NEAR = 0.01
DILATION = 0.3
CLAMP_MARGIN = 0.3
RADIUS_SIGMAS = 3.0
ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
ATTRIBUTES = tuple(f"a_{c}" for c in COLUMNS)  # vertex shader inputs of viewer.packing's columns


def clamp_limits(K: np.ndarray, width: int, height: int) -> tuple[float, float, float, float]:
    """gsplat's Jacobian clamp (x/z in [-lxn, lxp], y/z in [-lyn, lyp]), as in atgs.render."""
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    return (
        cx / fx + CLAMP_MARGIN * tan_x,
        (width - cx) / fx + CLAMP_MARGIN * tan_x,
        cy / fy + CLAMP_MARGIN * tan_y,
        (height - cy) / fy + CLAMP_MARGIN * tan_y,
    )


@dataclass
class RenderSettings:
    mode: RenderMode = "color"
    scale_modifier: float = 1.0
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    exact_sort: bool = False  # float argsort instead of the 16-bit radix sort
    environment: object | None = None
    """A background by direction (``atgs.render.environment.EnvironmentMap``: ``texels`` (H, W, 3),
    ``basis`` (3, 3)) drawn instead of ``background`` in colour mode, as the model trained over it."""
    min_alpha: float = ALPHA_MIN
    """Alpha cutoff: fragments below it are discarded, triangles shrink to where alpha can reach it,
    and Gaussians whose opacity is below it are culled before the draw. 1/255 (default) is the
    training rasterizer's rule; a larger cutoff trades accuracy for speed: no pixel loses more
    than ``min_alpha`` of alpha per Gaussian (measured PSNR in docs/viewer.md)."""

    def __post_init__(self) -> None:
        if not 0.0 < self.min_alpha < ALPHA_MAX:
            raise ValueError(f"min_alpha {self.min_alpha}: must be in (0, {ALPHA_MAX}); 1/255 is the rasterizer's cutoff")


@dataclass
class FrameTimings:
    """Milliseconds of the last frame's stages (0 when a stage was skipped)."""

    sort_ms: float = 0.0
    upload_ms: float = 0.0
    draw_ms: float = 0.0
    drawn: int = 0  # Gaussians that may touch the image (triangles drawn)
    sorted_again: bool = False


@dataclass
class _SortKey:
    w2c: bytes = b""
    version: int = -1
    exact: bool = False
    view: tuple = ()  # intrinsics, size, scale modifier, alpha cutoff and near plane (they change the cull)


@dataclass
class _Target:
    size: tuple[int, int]
    dtype: str
    texture: moderngl.Texture
    fbo: moderngl.Framebuffer


class SplatRenderer:
    """Draws :class:`PackedGaussians` for a :class:`Camera` into an offscreen float target.

    Use from the thread that owns ``ctx``. ``set_gaussians`` uploads; ``render`` sorts (if the
    camera or the data changed), draws, and returns nothing; ``read`` returns numpy images.
    ``near``: Gaussians at view z <= near are not drawn (whoever binds a source passes its
    near plane, ``atgs.model.near_plane.near_of``, so the player culls as training did).
    """

    def __init__(self, ctx: moderngl.Context, target_dtype: str = "f4", near: float = NEAR) -> None:
        self.ctx = ctx
        self.target_dtype = target_dtype  # "f4" exact; "f2" halves blend bandwidth for display
        self.near = float(near)
        self._programs: dict[int, moderngl.Program] = {}
        self.prog = self._program(-1)  # plain RGB: compiled up front, so a broken GL fails early
        self.present_prog = ctx.program(
            vertex_shader=load_shader("present.vert"), fragment_shader=load_shader("present.frag")
        )
        self.present_vao = ctx.vertex_array(self.present_prog, [])
        self.present_color_prog = ctx.program(
            vertex_shader=load_shader("present.vert"), fragment_shader=load_shader("present_color.frag")
        )
        self.present_color_vao = ctx.vertex_array(self.present_color_prog, [])
        self.environment_prog = ctx.program(
            vertex_shader=load_shader("present.vert"), fragment_shader=load_shader("environment.frag")
        )
        self.environment_vao = ctx.vertex_array(self.environment_prog, [])
        self._env_texture: moderngl.Texture | None = None
        self._env_source: object | None = None  # the map the texture holds
        self._columns: list[moderngl.Buffer | None] = [None] * (len(COLUMNS) + 1)  # + SH
        self._index_buf: moderngl.Buffer | None = None
        self._vao: moderngl.VertexArray | None = None
        self._vao_key: tuple = ()
        # a frame decoded on the GL (viewer.gl_decode.GLFrame): its columns stay in GL buffers,
        # and the order is sorted on the GL too (viewer.gl_sort), drawn by an indirect draw
        self._gl_frame: object | None = None
        self._gl_sort: object | None = None
        self._gl_order: object | None = None
        self._allocations = 0  # buffers made so far: the VAO is rebuilt when this changes
        self._sh_degree = -1
        self._count = 0
        self._version = 0
        self._sort_key = _SortKey()
        self._drawn = 0
        self._target: _Target | None = None
        self.timings = FrameTimings()
        self.gaussians: PackedGaussians | None = None
        self.depth_range = (0.0, 1.0)

    def _program(self, sh_degree: int) -> moderngl.Program:
        """The splat program for plain RGB (-1) or SH colour of a degree (compiled once, on first use)."""
        prog = self._programs.get(sh_degree)
        if prog is None:
            defines = {"SH_DEGREE": sh_degree}
            prog = self.ctx.program(
                vertex_shader=load_shader("splat.vert", defines),
                geometry_shader=load_shader("splat.geom"),
                fragment_shader=load_shader("splat.frag"),
            )
            self._programs[sh_degree] = prog
        return prog

    # --- data -----------------------------------------------------------------------------
    def _fit(self, buf: moderngl.Buffer | None, nbytes: int) -> moderngl.Buffer:
        """``buf`` if it holds ``nbytes``, else a new buffer with room to grow (powers of two)."""
        if buf is not None and buf.size >= nbytes:
            return buf
        if buf is not None:
            buf.release()
        self._allocations += 1
        return self.ctx.buffer(reserve=max(1 << max(0, (nbytes - 1).bit_length()), 4096), dynamic=True)

    def set_gaussians(self, packed: PackedGaussians) -> float:
        """Upload a frame's columns (one buffer write each); returns the upload time in ms."""
        t0 = time.perf_counter()
        n = len(packed)
        if n:
            for i, column in enumerate(packed.columns):
                self._columns[i] = buf = self._fit(self._columns[i], column.nbytes)
                buf.write(column)
        self._sh_degree = packed.sh_degree
        self._count = n
        self.gaussians = packed
        self._gl_frame = None
        self._version += 1
        ms = (time.perf_counter() - t0) * 1e3
        self.timings.upload_ms = ms
        return ms

    def set_frame(self, frame: object) -> None:
        """Show a frame: :class:`PackedGaussians` are uploaded, a GL-decoded frame is used in place."""
        if isinstance(frame, PackedGaussians):
            self.set_gaussians(frame)
        else:
            self.set_gl_frame(frame)

    @property
    def count(self) -> int:
        """Gaussians (GL-decoded frames: slots) of the current frame."""
        return self._count

    def set_gl_frame(self, frame: object) -> None:
        """Draw a frame decoded on the GL (:class:`viewer.gl_decode.GLFrame`: ``count`` Gaussians
        in the packing layout in its ``columns`` buffers): nothing is uploaded, and the depth sort
        runs on the GL as well (OpenGL 4.3)."""
        self._gl_frame = frame
        self.gaussians = None
        self._sh_degree = -1
        self._count = int(getattr(frame, "count"))
        self._version += 1
        self.timings.upload_ms = 0.0

    def drawn_count(self) -> int:
        """Gaussians that may touch the image in the last sort (a GL-sorted frame reads its count back)."""
        if self._gl_frame is not None and self._gl_order is not None and self._count:
            return int(self._gl_order.drawn())
        return self._drawn if self._count else 0

    def _vertex_array(self) -> moderngl.VertexArray | None:
        """The VAO of the current buffers and colour mode (rebuilt when either changed)."""
        if self._gl_frame is not None:  # the GL-decoded frame's columns and the GL sort's order
            if self._gl_order is None:
                return None
            used = list(getattr(self._gl_frame, "columns"))
            index, sh_format = self._gl_order.index_buffer, None
            # keyed by the buffer objects themselves (held by the key, so never reused by a new one)
            key: tuple = ("gl", tuple(used), index)
        else:
            g = self.gaussians
            if g is None or self._index_buf is None:
                return None
            used = self._columns[: len(g.columns)]
            index, sh_format = self._index_buf, None if g.sh is None else f"{g.sh.shape[1]}f2"
            # Keyed by allocation count, not GL names: NVIDIA's driver gives a new buffer the name of
            # the one just released, and a VAO kept for that name would still read the old (smaller)
            # buffer, which it keeps alive, and crash the process in the draw.
            key = (self._sh_degree, len(used), self._allocations)
        if self._vao is None or key != self._vao_key:
            if self._vao is not None:
                self._vao.release()
            content = [(buf, fmt, name) for buf, fmt, name in zip(used, COLUMN_FORMATS, ATTRIBUTES)]
            if sh_format is not None:
                content.append((used[-1], sh_format, "a_sh"))
            self._vao = self.ctx.vertex_array(self._program(self._sh_degree), content,
                                              index_buffer=index, index_element_size=4)
            self._vao_key = key
        return self._vao

    # --- targets --------------------------------------------------------------------------
    def _ensure_target(self, width: int, height: int) -> _Target:
        t = self._target
        if t is None or t.size != (width, height) or t.dtype != self.target_dtype:
            if t is not None:
                self._release_target(t)
            tex = self.ctx.texture((width, height), 4, dtype=self.target_dtype)
            tex.filter = (moderngl.LINEAR, moderngl.LINEAR)  # for presenting a reduced resolution
            self._target = t = _Target((width, height), self.target_dtype, tex, self.ctx.framebuffer([tex]))
        return t

    @property
    def target_texture(self) -> moderngl.Texture | None:
        return None if self._target is None else self._target.texture

    # --- sorting --------------------------------------------------------------------------
    def _sort(self, camera: Camera, exact: bool, scale_modifier: float = 1.0, min_alpha: float = ALPHA_MIN) -> None:
        key = camera.w2c.astype(np.float32).tobytes()
        view = (camera.K.tobytes(), camera.width, camera.height, float(scale_modifier), float(min_alpha), self.near)
        sk = self._sort_key
        if sk.w2c == key and sk.version == self._version and sk.exact == exact and sk.view == view:
            self.timings.sort_ms = 0.0
            self.timings.sorted_again = False
            return
        t0 = time.perf_counter()
        self._drawn = 0
        g = self.gaussians
        if self._gl_frame is not None and self._count:
            self._sort_on_gl(camera, scale_modifier, min_alpha)
        elif g is not None and self._count:
            # Off-screen Gaussians are dropped here (conservatively), and so are those too faint
            # to reach the alpha cutoff anywhere: they cost no vertex or setup work.
            cull = self._frustum_cull(camera, scale_modifier)
            order = back_to_front(g.means, camera.w2c, self.near, exact=exact, extent=g.extent, cull=cull,
                                  opacity=g.opacity, min_alpha=float(min_alpha))
            self._drawn = int(order.shape[0])
            if self._drawn:
                z = view_depths(g.means[order[[0, -1]].long()], camera.w2c).cpu()
                self.depth_range = (float(z[1]), float(z[0]))
                elements = order.cpu().numpy()  # one point per Gaussian, back to front
                self._index_buf = self._fit(self._index_buf, elements.nbytes)
                self._index_buf.write(elements)
        self._sort_key = _SortKey(key, self._version, exact, view)
        self.timings.sort_ms = (time.perf_counter() - t0) * 1e3
        self.timings.sorted_again = True

    @staticmethod
    def _frustum_cull(camera: Camera, scale_modifier: float) -> FrustumCull:
        """The screen-space cull of both sorts: the splat shader's extent, dilation and clamp."""
        return FrustumCull(camera.K, camera.width, camera.height, clamp_limits(camera.K, camera.width, camera.height),
                           scale_modifier=float(scale_modifier), sigmas=RADIUS_SIGMAS, dilation=DILATION)

    def _sort_on_gl(self, camera: Camera, scale_modifier: float, min_alpha: float) -> None:
        """The GL frame's order, on the GL (the count stays there: the draw is indirect)."""
        if self._gl_sort is None:
            from atgs.viewer.gl_sort import GLDepthSort

            self._gl_sort = GLDepthSort(self.ctx)
        cull = self._frustum_cull(camera, scale_modifier)
        means, _quat, scales, opacity_rgb = getattr(self._gl_frame, "columns")[:4]
        self._gl_order = self._gl_sort.sort(means, scales, opacity_rgb, self._count, camera.w2c, self.near, cull,
                                            float(min_alpha))
        self._drawn = -1  # known to the GL only (drawn_count() reads it back)

    # --- drawing --------------------------------------------------------------------------
    def render(self, camera: Camera, settings: RenderSettings | None = None, sync: bool = True) -> moderngl.Framebuffer:
        """Splat into the offscreen target of the camera's size; returns that framebuffer.

        ``sync`` waits for the GL with moderngl's finish (so ``timings.draw_ms`` is the draw).
        The window passes False and waits with ``viewer.gl_sync.gil_free_finish`` instead:
        moderngl's finish holds Python's GIL and would starve the decode thread."""
        s = settings or RenderSettings()
        if s.mode not in MODES:
            raise ValueError(f"unknown render mode {s.mode!r}; use one of {', '.join(MODES)}")
        W, H = camera.width, camera.height
        target = self._ensure_target(W, H)
        self._sort(camera, s.exact_sort, s.scale_modifier, s.min_alpha)
        t0 = time.perf_counter()
        fbo = target.fbo
        fbo.use()
        self.ctx.viewport = (0, 0, W, H)
        bg = (0.0, 0.0, 0.0) if s.mode == "depth" else tuple(float(c) for c in s.background)
        if s.mode == "color" and s.environment is not None:
            self._draw_environment(camera, s.environment)
        else:
            fbo.clear(bg[0], bg[1], bg[2], 0.0)
        vao = self._vertex_array() if self._count and self._drawn else None
        gl_order = self._gl_order if self._gl_frame is not None else None
        if gl_order is not None and s.mode == "depth":
            self.depth_range = gl_order.depth_range()  # the depth display's range (a readback)
        if vao is not None:
            uniforms = {
                "u_intr": (camera.fx, camera.fy, camera.cx, camera.cy),
                "u_size": (float(W), float(H)),
                "u_lim": clamp_limits(camera.K, W, H),
                "u_near": self.near,
                "u_dilation": DILATION,
                "u_scale_mod": float(s.scale_modifier),
                "u_campos": tuple(float(v) for v in camera.center),
                "u_extent": RADIUS_SIGMAS,
                "u_alpha_min": float(s.min_alpha),
                "u_alpha_max": ALPHA_MAX,
                "u_sigma_cut": 0.5 * RADIUS_SIGMAS**2,
                "u_mode": 1 if s.mode == "depth" else 0,
            }
            p = vao.program
            p["u_w2c"].write(np.ascontiguousarray(camera.w2c.T, dtype=np.float32).tobytes())
            for name, value in uniforms.items():
                member = p.get(name, None)
                if member is not None:  # a uniform the compiler removed is not an error
                    member.value = value
            self.ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
            self.ctx.enable(moderngl.BLEND)
            self.ctx.blend_equation = moderngl.FUNC_ADD
            self.ctx.blend_func = moderngl.ONE, moderngl.ONE_MINUS_SRC_ALPHA
            if gl_order is not None:
                vao.render_indirect(gl_order.indirect_buffer, moderngl.POINTS, count=1)
            else:
                vao.render(moderngl.POINTS, vertices=self._drawn)
            self.ctx.disable(moderngl.BLEND)
        if sync:
            self.ctx.finish()  # so that draw_ms measures the draw, not the next readback
        self.timings.draw_ms = (time.perf_counter() - t0) * 1e3
        self.timings.drawn = self._drawn if self._count else 0  # -1: a GL-sorted frame (drawn_count())
        return fbo

    def _draw_environment(self, camera: Camera, env: object) -> None:
        """Fill the bound target with the map's colour along each pixel's ray (alpha 0)."""
        if self._env_source is not env:
            texels = np.ascontiguousarray(np.asarray(getattr(env, "texels"), dtype=np.float32))
            if self._env_texture is not None:
                self._env_texture.release()
            tex = self.ctx.texture((texels.shape[1], texels.shape[0]), 3, texels.tobytes(), dtype="f4")
            tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
            tex.repeat_x, tex.repeat_y = True, False  # around in azimuth, clamped at the poles
            self._env_texture, self._env_source = tex, env
        basis = np.asarray(getattr(env, "basis"), dtype=np.float64).reshape(3, 3)
        cam_to_map = basis @ camera.R.T  # camera -> world -> map
        p = self.environment_prog
        self._env_texture.use(0)
        p["u_env"].value = 0
        p["u_intr"].value = (camera.fx, camera.fy, camera.cx, camera.cy)
        p["u_size"].value = (float(camera.width), float(camera.height))
        p["u_cam_to_map"].write(np.ascontiguousarray(cam_to_map.T, dtype=np.float32).tobytes())  # column major
        self.ctx.disable(moderngl.BLEND | moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        self.environment_vao.render(moderngl.TRIANGLES, vertices=3)

    def read(self) -> np.ndarray:
        """The target as (H, W, 4) float32, top row first: premultiplied rgb (or z*alpha) and alpha."""
        if self._target is None:
            raise RuntimeError("nothing rendered yet")
        W, H = self._target.size
        raw = self._target.fbo.read(components=4, dtype="f4")
        return np.frombuffer(raw, dtype=np.float32).reshape(H, W, 4)[::-1].copy()

    def render_image(self, camera: Camera, settings: RenderSettings | None = None) -> np.ndarray:
        """Render and read back (float32), the same quantities as :func:`atgs.render.rasterize`:
        color (H,W,3) = C + T bg, depth (H,W) = sum_i z_i alpha_i T_i, alpha (H,W) = 1 - T."""
        s = settings or RenderSettings()
        self.render(camera, s)
        img = self.read()
        if s.mode == "color":
            return img[..., :3]
        if s.mode == "alpha":
            return img[..., 3]
        return img[..., 0]

    def present(
        self, fbo: moderngl.Framebuffer, viewport: tuple[int, int, int, int], settings: RenderSettings
    ) -> None:
        """Draw the offscreen target into ``fbo`` (e.g. the window) with the display mapping."""
        if self._target is None:
            return
        fbo.use()
        self.ctx.viewport = viewport
        self._target.texture.use(0)
        self.ctx.disable(moderngl.BLEND | moderngl.DEPTH_TEST)
        if settings.mode == "color":  # the target's rgb is already the image
            self.present_color_prog["u_image"].value = 0
            self.present_color_vao.render(moderngl.TRIANGLES, vertices=3)
            return
        p = self.present_prog
        p["u_image"].value = 0
        p["u_mode"].value = MODES.index(settings.mode)
        p["u_range"].value = self.depth_range
        p["u_background"].value = tuple(float(c) for c in settings.background)
        self.present_vao.render(moderngl.TRIANGLES, vertices=3)

    @staticmethod
    def _release_target(t: _Target) -> None:
        for obj in (t.fbo, t.texture):
            obj.release()

    def release(self) -> None:
        if self._gl_sort is not None:
            self._gl_sort.release()
        for obj in (self._vao, self._index_buf, *self._columns, self.present_vao, *self._programs.values(),
                    self.present_prog, self.present_color_vao, self.present_color_prog, self.environment_vao,
                    self.environment_prog, self._env_texture):
            if obj is not None:
                obj.release()
        if self._target is not None:
            self._release_target(self._target)
            self._target = None

