"""The player window: glfw (OpenGL 3.3 core) + moderngl splatting + imgui-bundle controls.

Keyboard (when the UI does not have focus):
  Space play/pause   Left/Right step one frame   Home/End first/last frame   L loop
  -/= speed down/up   1/2/3 color/depth/alpha   [/] scale modifier   C next training camera
  R reset camera   F fly mode   WASD/QE fly   P or F12 screenshot   H hide UI   Esc quit
  K add a camera-path keyframe   V preview the path   Delete remove the keyframe   Ctrl+S save the path
Mouse: left drag orbit (fly mode: look), right/middle drag or shift+left pan, wheel zoom.
"""

from __future__ import annotations

import ctypes
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from atgs.errors import UserError
from atgs.model.near_plane import near_of
from atgs.viewer.adaptive import TARGET_MS, next_render_scale
from atgs.viewer.camera_control import CameraControl
from atgs.viewer.decode_cache import DecodeCache
from atgs.viewer.errors import ViewerError
from atgs.viewer.gl_sync import gil_free_finish
from atgs.viewer.output import display_rgb, save_image, to_uint8
from atgs.viewer.packing import PackedGaussians
from atgs.viewer.path_panel import PathPanel
from atgs.viewer.playback import FrameFeeder, Playback
from atgs.viewer.scene_utils import orbit_center, parse_size, start_camera
from atgs.viewer.source import GaussianSource, decode_frame, scene_up
from atgs.viewer.splat_renderer import MODES, RenderSettings, SplatRenderer
from atgs.viewer.window_size import default_window_size, screen_work_area

SPEEDS = (0.125, 0.25, 0.5, 1.0, 2.0, 4.0)
# UI frame cap: an idle loop that spins holds the GIL and starves the decode thread (a decode
# of ~20 ms took 200-300 ms while the loop spun); sleeping out the rest of the frame frees it.
MAX_UI_FPS = 60.0


@dataclass
class Stats:
    """Smoothed per-frame timings for the overlay (exponential moving averages, ms)."""

    frame_ms: float = 0.0
    sort_ms: float = 0.0
    draw_ms: float = 0.0
    upload_ms: float = 0.0
    decode_ms: float = 0.0
    shown_frames: list[int] = field(default_factory=list)

    def push(self, name: str, value: float, k: float = 0.1) -> None:
        old = getattr(self, name)
        setattr(self, name, value if old == 0.0 else (1 - k) * old + k * value)

    @property
    def fps(self) -> float:
        return 1000.0 / self.frame_ms if self.frame_ms > 0 else 0.0


def _glfw_error(glfw) -> str:
    code, desc = glfw.get_error()
    if not code:
        return "no display?"
    return desc.decode(errors="replace") if isinstance(desc, bytes) else str(desc)


class PlayerApp:
    """One window playing one source. ``step(dt)`` runs a UI frame; ``run()`` loops until closed."""

    def __init__(self, source: GaussianSource, camera_index: int = 0, size: str | None = None,
                 settings: RenderSettings | None = None, visible: bool = True,
                 preloaded: dict[int, PackedGaussians] | None = None, cache_mb: int = 1024,
                 device: torch.device | str = "cpu", path_file: str | Path | None = None,
                 decode: str = "torch") -> None:
        import imgui_bundle  # noqa: F401  (first: makes pyGLFW use imgui-bundle's libglfw)
        import glfw
        import moderngl
        from imgui_bundle import imgui

        self.glfw, self.imgui = glfw, imgui
        self.source = source
        cam0 = start_camera(source, camera_index)
        self.cameras = list(source.cameras) or [cam0]
        self.cam_index = camera_index if source.cameras else 0
        self.paths = PathPanel(self, path_file)  # camera-path keyframes; loads path_file if it exists

        glfw.ERROR_REPORTING = "ignore"  # failures become one ViewerError line, not warnings
        if not glfw.init():
            raise ViewerError(
                f"cannot initialise GLFW ({_glfw_error(glfw)}); use --headless, or run under xvfb-run -a"
            )
        width, height = parse_size(size) or default_window_size((cam0.width, cam0.height), screen_work_area(glfw))
        glfw.window_hint(glfw.CONTEXT_VERSION_MAJOR, 3)
        glfw.window_hint(glfw.CONTEXT_VERSION_MINOR, 3)
        glfw.window_hint(glfw.OPENGL_PROFILE, glfw.OPENGL_CORE_PROFILE)
        glfw.window_hint(glfw.OPENGL_FORWARD_COMPAT, True)
        glfw.window_hint(glfw.VISIBLE, bool(visible))
        glfw.window_hint(glfw.ALPHA_BITS, 0)  # the color present writes coverage into alpha: keep it off screen
        self.window = glfw.create_window(width, height, "ATGS viewer", None, None)
        if not self.window:
            glfw.terminate()
            raise ViewerError(
                f"cannot open an OpenGL 3.3 core window ({_glfw_error(glfw)}); "
                "use --headless, or run under xvfb-run -a, or update Mesa / the GPU driver"
            )
        glfw.make_context_current(self.window)
        glfw.swap_interval(0)
        try:
            self.ctx = moderngl.create_context(require=330)
        except Exception as exc:
            self._terminate()
            raise ViewerError(f"OpenGL 3.3 core is required ({str(exc).strip().splitlines()[0]}); update Mesa or the GPU driver") from None
        self.gl_info = f"{self.ctx.info.get('GL_RENDERER', '?')}, {self.ctx.info.get('GL_VERSION', '?')}"

        imgui.create_context()
        imgui.get_io().set_ini_filename("")  # no imgui.ini next to the user's files
        imgui.style_colors_dark()
        addr = ctypes.cast(self.window, ctypes.c_void_p).value
        imgui.backends.glfw_init_for_opengl(addr, True)
        imgui.backends.opengl3_init("#version 330")

        self.renderer = SplatRenderer(self.ctx, near=near_of(source))  # the model's near plane
        self._gl_finish = gil_free_finish(self.ctx.finish)
        self.settings = settings or RenderSettings()
        self.playback = Playback(num_frames=source.num_frames, fps=float(source.fps or 30.0))
        gl_decoding = decode == "gl"
        self.cache = DecodeCache(lambda f: decode_frame(source, f, device), capacity=8, pinned=preloaded,
                                 keep_bytes=0 if gl_decoding else max(0, cache_mb) << 20)
        self.feeder = self._gl_feeder(source) if gl_decoding else FrameFeeder(self.cache, lookahead=4)
        if not gl_decoding:
            self.cache.prefetch(range(source.num_frames))  # fill --cache-mb in the background
        self.center = orbit_center(source)
        self.control = CameraControl.from_camera(cam0, pivot=self.center, up=scene_up(self.cameras))
        self.fly_mode = False
        self.fly_speed = 0.5 * max(self.control.state.distance, 1e-3)  # world units per second
        self.render_scale = 1.0
        self.adaptive = True  # adaptive resolution (UI checkbox): lower while playing/moving, full when still
        self.target_ms = TARGET_MS  # 25 FPS
        self._last_key: tuple | None = None
        self._last_scale = 1.0
        self.show_ui = True
        self.stats = Stats()
        self.message = ""
        self.screenshot_dir = Path(".")
        self._last_time = time.perf_counter()
        self._anchors = -1
        self._closed = False

    def _gl_feeder(self, source: GaussianSource):
        """Frames decoded on the GL (``--decode gl``), or a one-line error saying why not."""
        from atgs.viewer.gl_decode import GLFrameFeeder, gl_decoder_for

        try:
            return GLFrameFeeder(gl_decoder_for(self.ctx, source))
        except ViewerError:
            self._terminate()
            raise

    # --- main loop ---------------------------------------------------------------------------
    def run(self) -> None:
        glfw = self.glfw
        while not glfw.window_should_close(self.window):
            now = time.perf_counter()
            dt, self._last_time = now - self._last_time, now
            self.step(min(dt, 0.25))
            rest_until(now + 1.0 / MAX_UI_FPS)

    def step(self, dt: float) -> None:
        """One UI frame: input, playback, decode feed, splat, UI, swap."""
        glfw, imgui = self.glfw, self.imgui
        t_start = time.perf_counter()
        glfw.poll_events()
        imgui.backends.opengl3_new_frame()
        imgui.backends.glfw_new_frame()
        imgui.new_frame()
        self._handle_input(dt)
        self.playback.advance(dt)
        self.paths.update(dt)  # a path preview moves the view and the playhead
        packed, changed = self.feeder.update(self.playback)
        if changed and packed is not None:
            self.renderer.set_frame(packed)
            self.stats.push("upload_ms", self.renderer.timings.upload_ms)
            self.stats.push("decode_ms", packed.decode_ms)
            self._anchors = packed.num_anchors
        if packed is not None:
            self.stats.shown_frames.append(packed.frame)
        fb_w, fb_h = self._framebuffer_size()
        drew, wait_ms = False, 0.0
        if fb_w > 0 and fb_h > 0:
            drew = self._render_view(fb_w, fb_h)
            self.feeder.after_draw(self.playback)  # the GL feeder decodes the next frame behind the draw
            if drew:  # wait for the splat here, GIL released, so the decode thread keeps running
                t_wait = time.perf_counter()
                self._gl_finish()
                wait_ms = (time.perf_counter() - t_wait) * 1e3
            self.ctx.screen.use()
            self.ctx.viewport = (0, 0, fb_w, fb_h)
            if self.renderer.target_texture is None:  # else the present covers every pixel
                self.ctx.screen.clear(*self.settings.background, 1.0)
            self.renderer.present(self.ctx.screen, (0, 0, fb_w, fb_h), self.settings)
        if self.show_ui:
            self._draw_ui()
        imgui.render()
        imgui.backends.opengl3_render_draw_data(imgui.get_draw_data())
        t_swap = time.perf_counter()
        glfw.swap_buffers(self.window)  # llvmpipe finishes the frame here, with the GIL released
        frame_ms = (time.perf_counter() - t_start) * 1e3
        if drew:
            draw_ms = self.renderer.timings.draw_ms + wait_ms + (time.perf_counter() - t_swap) * 1e3
            self.stats.push("draw_ms", draw_ms)
            # The budget is the whole UI frame (splat, present, UI, swap): that is what the
            # frame rate is made of, and the rest costs ~10 ms on llvmpipe.
            self._adapt_resolution(frame_ms)
        self.stats.push("frame_ms", frame_ms)

    def _framebuffer_size(self) -> tuple[int, int]:
        """The window's framebuffer size as imgui's glfw backend read it this frame (asking
        glfw again is an X server round trip: ~0.5 ms each under Xvfb here)."""
        io = self.imgui.get_io()
        scale = io.display_framebuffer_scale
        return int(round(io.display_size.x * scale.x)), int(round(io.display_size.y * scale.y))

    def _render_view(self, fb_w: int, fb_h: int) -> bool:
        """Splat the view if anything changed (else the last image is presented again); while
        nothing changes, one full-resolution pass replaces an adaptive low-resolution one."""
        s = self.settings
        cam_full = self.control.camera(fb_w, fb_h)
        shown = self.feeder.shown
        key = (cam_full.w2c.tobytes(), cam_full.K.tobytes(), fb_w, fb_h, id(shown), s.mode,
               s.scale_modifier, s.min_alpha, tuple(s.background), self.adaptive or self.render_scale)
        scale = self.render_scale
        if key == self._last_key:
            if self._last_scale >= 1.0 or not self.adaptive:
                return False
            scale = 1.0  # idle: refine to full resolution once
        rw, rh = max(1, int(fb_w * scale)), max(1, int(fb_h * scale))
        cam = self.control.camera(rw, rh)
        # 8-bit blending is llvmpipe's fast path (~20% faster than float) and the screen is 8 bit;
        # depth needs a float target (z * alpha is not in [0, 1]).
        self.renderer.target_dtype = "f2" if s.mode == "depth" else "f1"
        self.renderer.render(cam, s, sync=False)
        if self.renderer.timings.sorted_again:
            self.stats.push("sort_ms", self.renderer.timings.sort_ms)
        self._last_key, self._last_scale = key, scale
        return True

    def _adapt_resolution(self, frame_ms: float) -> None:
        """Adaptive resolution: keep UI frames under ``target_ms`` while playing or moving."""
        if not self.adaptive or self._last_scale != self.render_scale:
            return
        self.render_scale = next_render_scale(self.render_scale, frame_ms, self.target_ms)

    # --- input -------------------------------------------------------------------------------
    def _handle_input(self, dt: float) -> None:
        imgui = self.imgui
        io = imgui.get_io()
        K = imgui.Key
        if not io.want_capture_keyboard:
            pb = self.playback
            if imgui.is_key_pressed(K.space, False):
                pb.toggle()
            if imgui.is_key_pressed(K.right_arrow):
                pb.step(1)
            if imgui.is_key_pressed(K.left_arrow):
                pb.step(-1)
            if imgui.is_key_pressed(K.home, False):
                pb.seek_frame(0)
            if imgui.is_key_pressed(K.end, False):
                pb.seek_frame(pb.num_frames - 1)
            if imgui.is_key_pressed(K.l, False):
                pb.loop = not pb.loop
            if imgui.is_key_pressed(K.equal, False):
                self._change_speed(1)
            if imgui.is_key_pressed(K.minus, False):
                self._change_speed(-1)
            for i, key in enumerate((K._1, K._2, K._3)):
                if imgui.is_key_pressed(key, False):
                    self.settings.mode = MODES[i]  # type: ignore[assignment]
            if imgui.is_key_pressed(K.right_bracket):
                self.settings.scale_modifier = min(4.0, self.settings.scale_modifier * 1.1)
            if imgui.is_key_pressed(K.left_bracket):
                self.settings.scale_modifier = max(0.05, self.settings.scale_modifier / 1.1)
            if imgui.is_key_pressed(K.c, False):
                self.snap_to_camera((self.cam_index + 1) % len(self.cameras))
            if imgui.is_key_pressed(K.r, False):
                self.control.reset()
            if imgui.is_key_pressed(K.f, False):
                self.fly_mode = not self.fly_mode
            if imgui.is_key_pressed(K.p, False) or imgui.is_key_pressed(K.f12, False):
                self.screenshot()
            if imgui.is_key_pressed(K.h, False):
                self.show_ui = not self.show_ui
            if imgui.is_key_pressed(K.escape, False):
                self.glfw.set_window_should_close(self.window, True)
            self.paths.handle_keys()
            if self.fly_mode:
                step = self.fly_speed * dt
                mv = lambda a, b: (1.0 if imgui.is_key_down(a) else 0.0) - (1.0 if imgui.is_key_down(b) else 0.0)  # noqa: E731
                f, r, u = mv(K.w, K.s), mv(K.d, K.a), mv(K.e, K.q)
                if f or r or u:
                    self.control.fly(f * step, r * step, u * step)
        if not io.want_capture_mouse:
            d = io.mouse_delta
            _, fb_h = self._framebuffer_size()
            shift = io.key_shift
            if imgui.is_mouse_down(0) and not shift and (d.x or d.y):
                if self.fly_mode:
                    self.control.look(-d.x * 0.004, -d.y * 0.004)
                else:
                    self.control.orbit(-d.x * 0.008, d.y * 0.008)
            elif (imgui.is_mouse_down(1) or imgui.is_mouse_down(2) or (shift and imgui.is_mouse_down(0))) and (d.x or d.y):
                self.control.pan(d.x, d.y, max(fb_h, 1))
            if io.mouse_wheel:
                self.control.zoom(io.mouse_wheel)

    def _change_speed(self, direction: int) -> None:
        sp = abs(self.playback.speed)
        i = min(range(len(SPEEDS)), key=lambda k: abs(SPEEDS[k] - sp))
        self.playback.speed = SPEEDS[min(len(SPEEDS) - 1, max(0, i + direction))]

    # --- actions -----------------------------------------------------------------------------
    def snap_to_camera(self, index: int) -> None:
        self.cam_index = index
        self.control.snap(self.cameras[index], pivot=self.center)

    def screenshot(self, path: str | Path | None = None) -> Path:
        """Save the splatted image (without the UI) at the render resolution."""
        if path is None:
            path = self.screenshot_dir / f"atgs_frame{self.playback.frame:06d}_{time.strftime('%Y%m%d-%H%M%S')}.png"
        fb_w, fb_h = self.glfw.get_framebuffer_size(self.window)
        self.renderer.render(self.control.camera(max(fb_w, 1), max(fb_h, 1)), self.settings)
        self._last_key = None  # the target now holds this render; redo the view next frame
        raw = self.renderer.read()
        try:
            save_image(path, to_uint8(display_rgb(raw, self.settings.mode, self.settings.background)))
        except (OSError, UserError) as exc:  # a full disk or a bad path must not close the player
            self.message = f"screenshot failed: {exc}"
            return Path(path)
        self.message = f"saved {path}"
        return Path(path)

    def read_window(self) -> np.ndarray:
        """The window's back buffer (splats + UI) as (H, W, 3) uint8, top row first."""
        fb_w, fb_h = self.glfw.get_framebuffer_size(self.window)
        raw = self.ctx.screen.read(viewport=(0, 0, fb_w, fb_h), components=3)
        return np.frombuffer(raw, np.uint8).reshape(fb_h, fb_w, 3)[::-1].copy()

    # --- UI ------------------------------------------------------------------------------------
    def _draw_ui(self) -> None:
        """Player layout: a scrub bar along the bottom, a statistics overlay top left and a
        collapsible settings panel top right (collapsed at first in small windows)."""
        imgui = self.imgui
        W = imgui.get_io().display_size.x
        H = imgui.get_io().display_size.y
        self._draw_scrub_bar(W, H)
        self._draw_stats()
        self._draw_settings(W)
        below_stats = 6 + 5 * imgui.get_text_line_height_with_spacing() + 2 * imgui.get_style().window_padding.y
        self.paths.draw(below_stats + (imgui.get_frame_height_with_spacing() if W < 900 else 0))

    def _draw_scrub_bar(self, W: float, H: float) -> None:
        imgui = self.imgui
        pb = self.playback
        F = imgui.WindowFlags_
        bar_h = 2 * imgui.get_frame_height_with_spacing() + 2 * imgui.get_style().window_padding.y
        imgui.set_next_window_pos((0, H - bar_h))
        imgui.set_next_window_size((W, bar_h))
        imgui.set_next_window_bg_alpha(0.7)
        imgui.begin("timeline", None, F.no_decoration | F.no_move | F.no_saved_settings)
        if imgui.button("Pause" if pb.playing else "Play"):
            pb.toggle()
        imgui.same_line()
        if imgui.button("<"):
            pb.step(-1)
        imgui.same_line()
        if imgui.button(">"):
            pb.step(1)
        imgui.same_line()
        imgui.set_next_item_width(-1)
        changed, f = imgui.slider_int("##frame", pb.frame, 0, max(0, pb.num_frames - 1), f"frame %d / {pb.num_frames - 1}")
        if changed:
            pb.seek_frame(f)
        imgui.set_next_item_width(max(60.0, W - 260.0))
        changed, t = imgui.slider_float("##time", pb.time, 0.0, 1.0, f"t = %.4f   ({pb.frame / max(pb.fps, 1e-9):.2f} s)")
        if changed:
            pb.seek_time(t)
        imgui.same_line()
        labels = [f"{v:g}x" for v in SPEEDS]
        cur = min(range(len(SPEEDS)), key=lambda k: abs(SPEEDS[k] - abs(pb.speed)))
        imgui.set_next_item_width(70)
        changed, i = imgui.combo("##speed", cur, labels)
        if changed:
            pb.speed = SPEEDS[i]
        imgui.same_line()
        _, pb.loop = imgui.checkbox("loop", pb.loop)
        imgui.end()

    def _draw_stats(self) -> None:
        imgui = self.imgui
        F = imgui.WindowFlags_
        imgui.set_next_window_pos((6, 6))
        imgui.set_next_window_bg_alpha(0.45)
        flags = F.no_decoration | F.no_move | F.no_saved_settings | F.always_auto_resize | F.no_inputs
        imgui.begin("stats", None, flags)
        st = self.stats
        n = self.renderer.count
        anchors = "?" if self._anchors < 0 else f"{self._anchors}"
        imgui.text(f"{st.fps:5.1f} FPS  ({st.frame_ms:.0f} ms)   res x{self.render_scale:.2f}")
        imgui.text(f"decode {st.decode_ms:.0f}  sort {st.sort_ms:.1f}  upload {st.upload_ms:.1f}  draw {st.draw_ms:.0f} ms")
        imgui.text(f"anchors {anchors}  Gaussians {n} ({self.renderer.drawn_count()} drawn)")
        if self.cache.last_error:
            imgui.text(self.cache.last_error)
        if self.message:
            imgui.text(self.message)
        imgui.end()

    def _draw_settings(self, W: float) -> None:
        imgui = self.imgui
        small = W < 900
        # In a small window the (collapsed) panel goes below the statistics instead of over them.
        y = 6 + (5 * imgui.get_text_line_height_with_spacing() + 2 * imgui.get_style().window_padding.y if small else 0)
        imgui.set_next_window_pos((W - 6, y), imgui.Cond_.first_use_ever, (1.0, 0.0))
        imgui.set_next_window_collapsed(small, imgui.Cond_.first_use_ever)
        imgui.set_next_window_bg_alpha(0.75)
        imgui.begin("view (H hides the UI)", None, imgui.WindowFlags_.always_auto_resize)
        names = [c.name for c in self.cameras]
        changed, i = imgui.combo("camera", self.cam_index, names)
        if changed:
            self.snap_to_camera(i)
        changed, fov = imgui.slider_float("fov", math.degrees(self.control.state.fov_y), 10.0, 120.0, "%.1f deg")
        if changed:
            self.control.set_fov(fov)
        _, self.fly_mode = imgui.checkbox("fly (WASD/QE)", self.fly_mode)
        imgui.same_line()
        if imgui.button("reset view"):
            self.control.reset()
        imgui.separator()
        changed, m = imgui.combo("mode", MODES.index(self.settings.mode), list(MODES))
        if changed:
            self.settings.mode = MODES[m]  # type: ignore[assignment]
        _, self.settings.scale_modifier = imgui.slider_float("scale", self.settings.scale_modifier, 0.05, 4.0, "%.2f")
        # alpha cutoff in 1/255 steps: 1 is the rasterizer's rule; higher culls faint splats (faster)
        changed, cut = imgui.slider_int("alpha cutoff /255", round(self.settings.min_alpha * 255), 1, 16)
        if changed:
            self.settings.min_alpha = cut / 255.0
        _, self.adaptive = imgui.checkbox("adaptive resolution", self.adaptive)
        if not self.adaptive:
            _, self.render_scale = imgui.slider_float("resolution", self.render_scale, 0.25, 1.0, "%.2f")
        if imgui.button("screenshot (P)"):
            self.screenshot()
        imgui.separator()
        imgui.text(f"cached frames {len(self.cache.cached_frames())}")
        imgui.text(self.gl_info)
        imgui.end()

    # --- teardown ------------------------------------------------------------------------------
    def _terminate(self) -> None:
        self.glfw.destroy_window(self.window)
        self.glfw.terminate()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.cache.close()
        self.feeder.close()
        self.imgui.backends.opengl3_shutdown()
        self.imgui.backends.glfw_shutdown()
        self.imgui.destroy_context()
        self.renderer.release()
        self._terminate()


def rest_until(t: float) -> None:
    """Sleep (GIL released) until perf_counter() reaches t; return at once if it has."""
    left = t - time.perf_counter()
    if left > 0:
        time.sleep(left)


def preload_frames(source: GaussianSource, limit_mb: int,
                   device: torch.device | str = "cpu") -> dict[int, PackedGaussians]:
    """Decode all frames up front (tqdm bar); refuses sequences that would exceed ``limit_mb``."""
    from atgs.progress import progress_bar

    F = source.num_frames
    first = decode_frame(source, 0, device)
    est_mb = F * first.nbytes / 2**20
    if est_mb > limit_mb:
        raise ViewerError(f"--preload needs about {est_mb:.0f} MB for {F} frames; raise --preload-mb or drop --preload")
    out = {0: first}
    with progress_bar(F, "decoding frames", unit="frame") as bar:
        bar.update(1)
        for f in range(1, F):
            out[f] = decode_frame(source, f, device)
            bar.update(1)
    return out
