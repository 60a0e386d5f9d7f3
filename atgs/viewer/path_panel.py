"""The player's camera-path panel: record keyframes where you look, preview the fly-through,
save it for ``atgs-render --path FILE.json``. imgui-bundle UI over :class:`PathEditor`.

Keys (when the UI does not have the keyboard): K add a keyframe at the current view and playhead
time, V preview the path (again: stop), Delete remove the selected keyframe, Ctrl+S save.
While previewing, the view and the playhead follow the path frame by frame exactly as
``atgs-render`` renders it (same cameras, same sequence frames), at the window's size.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from atgs.viewer.camera_path import PathKey
from atgs.viewer.camera_path_file import load_camera_path, save_camera_path
from atgs.viewer.errors import ViewerError
from atgs.viewer.path_editor import PathEditor

if TYPE_CHECKING:  # the app imports this module; no import cycle at run time
    from atgs.viewer.app import PlayerApp

DEFAULT_FILE = "camera_path.json"
OVERLAY_SAMPLES = 24  # points per segment of the drawn path


class PathPanel:
    def __init__(self, app: "PlayerApp", file: str | Path | None = None) -> None:
        """``file``: the path file Save writes and Load reads; loaded now if it exists."""
        self.app = app
        self.editor = PathEditor()
        self.file = str(file) if file is not None else DEFAULT_FILE
        self.open_request: bool | None = None  # expand (True) / collapse (False) the panel next frame
        self._overlay: tuple[int, np.ndarray] | None = None  # (editor revision, world points)
        self._shown_frame = -1
        if file is not None and Path(file).exists():
            self.editor.replace_path(load_camera_path(file))  # a broken file: one-line error, exit 2

    # --- actions (keys and buttons) ----------------------------------------------------------
    def view_key(self) -> PathKey:
        """A keyframe at the current view and playhead time (its video_t is set by the editor)."""
        ctl = self.app.control
        w2c = ctl.camera(16, 16).w2c  # the pose only: intrinsics follow from fov and render size
        return PathKey(0.0, w2c, math.degrees(ctl.state.fov_y), self.app.playback.time)

    def add_keyframe(self) -> None:
        i = self.editor.add(self.view_key())
        self.open_request = True
        self.app.message = f"keyframe {i + 1} of {len(self.editor.keys)} added"

    def go_to(self, i: int) -> None:
        """Move the view and the playhead to keyframe i."""
        k = self.editor.keys[i]
        self.editor.stop_preview()
        self._set_view(k.eye, k.R, k.fov_y_deg, k.scene_t)

    def toggle_preview(self) -> None:
        ed = self.editor
        if ed.previewing:
            ed.stop_preview()
        elif not ed.keys:
            self.app.message = "add keyframes (K) before previewing"
        else:
            ed.start_preview()
            self._shown_frame = -1

    def save(self) -> bool:
        ed = self.editor
        fb_w, fb_h = self._framebuffer_size()
        if fb_w >= 16 and fb_h >= 16:  # the preview's size (even, for H.264) is the default video size
            ed.path.size = (fb_w - fb_w % 2, fb_h - fb_h % 2)
        try:
            save_camera_path(ed.path, self.file)
        except (OSError, ViewerError) as exc:  # a full disk or a bad name must not close the player
            self.app.message = f"path not saved: {exc}"
            return False
        self.app.message = f"saved {self.file}"
        return True

    def load(self) -> bool:
        try:
            self.editor.replace_path(load_camera_path(self.file))
        except ViewerError as exc:
            self.app.message = str(exc)
            return False
        self.app.message = f"loaded {self.file} ({len(self.editor.keys)} keyframes)"
        return True

    # --- per UI frame ------------------------------------------------------------------------
    def handle_keys(self) -> None:
        """Shortcuts; the app calls this only when imgui does not want the keyboard."""
        imgui = self.app.imgui
        K = imgui.Key
        if imgui.is_key_pressed(K.k, False):
            self.add_keyframe()
        if imgui.is_key_pressed(K.v, False):
            self.toggle_preview()
        if imgui.is_key_pressed(K.delete, False) and self.editor.selected is not None:
            self.editor.delete(self.editor.selected)
        if imgui.get_io().key_ctrl and imgui.is_key_pressed(K.s, False):
            self.save()

    def update(self, dt: float) -> None:
        """Advance the preview; put the view and playhead on the path's current frame."""
        ed = self.editor
        was_previewing = ed.previewing
        ed.advance(dt)
        if (was_previewing or ed.previewing) and ed.frame != self._shown_frame:
            self.show_frame(ed.frame)

    def show_frame(self, frame: int) -> None:
        """The view of video frame ``frame`` of the path: its camera and its sequence frame."""
        ed = self.editor
        ed.frame = frame
        pose = ed.path.pose_at(ed.video_t)
        self._set_view(pose.eye, pose.R, pose.fov_y_deg, pose.scene_t)
        self._shown_frame = frame

    def _set_view(self, eye: np.ndarray, R: np.ndarray, fov_y_deg: float, scene_t: float) -> None:
        st = self.app.control.state
        st.eye, st.R, st.fov_y = np.array(eye, dtype=np.float64), np.array(R, dtype=np.float64), math.radians(fov_y_deg)
        depth = float((self.app.center - st.eye) @ st.R[2])  # orbit on around the scene center, as after a camera snap
        if depth > 1e-3:
            st.distance = depth
        pb = self.app.playback
        pb.playing = False
        pb.seek_time(scene_t)  # the sequence frame atgs-render shows: frame_at(scene_t)

    def _framebuffer_size(self) -> tuple[int, int]:
        io = self.app.imgui.get_io()
        scale = io.display_framebuffer_scale
        return int(round(io.display_size.x * scale.x)), int(round(io.display_size.y * scale.y))

    # --- drawing -----------------------------------------------------------------------------
    def draw(self, y: float) -> None:
        """The panel (left, from height ``y``) and the path drawn into the view."""
        imgui = self.app.imgui
        self._draw_overlay()
        imgui.set_next_window_pos((6, y), imgui.Cond_.first_use_ever)
        imgui.set_next_window_collapsed(True, imgui.Cond_.first_use_ever)
        if self.open_request is not None:
            imgui.set_next_window_collapsed(not self.open_request, imgui.Cond_.always)
            self.open_request = None
        imgui.set_next_window_bg_alpha(0.75)
        if imgui.begin("camera path (K key, V preview)", None, imgui.WindowFlags_.always_auto_resize)[0]:
            self._draw_keyframes()
            self._draw_timing()
            self._draw_file()
        imgui.end()

    def _draw_keyframes(self) -> None:
        imgui, ed = self.app.imgui, self.editor
        if imgui.button("add (K)"):
            self.add_keyframe()
        sel = ed.selected
        imgui.begin_disabled(sel is None)
        for label, action in (("update", lambda i: ed.update(i, self.view_key())), ("delete", ed.delete),
                              ("up", lambda i: ed.move(i, -1)), ("down", lambda i: ed.move(i, 1))):
            imgui.same_line()
            if imgui.button(label) and sel is not None:
                action(sel)
        imgui.end_disabled()
        labels = [f"{i + 1:2d}   at {k.video_t:5.3f}   scene t {k.scene_t:5.3f}   fov {k.fov_y_deg:5.1f}"
                  for i, k in enumerate(ed.keys)]
        width = imgui.calc_text_size(labels[0] if labels else "").x + 2 * imgui.get_style().frame_padding.x + 16
        rows = min(6, max(2, len(ed.keys)))
        if imgui.begin_list_box("##keys", (max(width, 200.0), rows * imgui.get_text_line_height_with_spacing() + 6)):
            for i, (k, label) in enumerate(zip(ed.keys, labels)):
                clicked, _ = imgui.selectable(f"{label}##key{i}", i == ed.selected)
                if clicked:  # select and move there
                    ed.selected = i
                    self.go_to(i)
            imgui.end_list_box()
        if sel is not None and sel < len(ed.keys):
            k = ed.keys[sel]
            if not ed.even_timing:
                changed, v = imgui.slider_float("video t", k.video_t, 0.0, 1.0, "%.3f")
                if changed:
                    ed.set_video_t(sel, v)
            changed, v = imgui.slider_float("scene t", k.scene_t, 0.0, 1.0, "%.3f")
            if changed:
                ed.set_scene_t(sel, v)
            imgui.same_line()
            if imgui.button("= playhead"):
                ed.set_scene_t(sel, self.app.playback.time)

    def _draw_timing(self) -> None:
        imgui, ed = self.app.imgui, self.editor
        changed, on = imgui.checkbox("even timing", ed.even_timing)
        if changed:
            ed.set_even_timing(on)
        imgui.same_line()
        if imgui.button("scene time follows the path"):
            ed.spread_scene_time()
        imgui.set_next_item_width(110)
        changed, v = imgui.input_float("duration s", ed.path.duration_s, 0.5, 5.0, "%.2f")
        if changed and v > 0:
            ed.set_timing(duration_s=v)
        imgui.same_line()
        imgui.set_next_item_width(90)
        changed, v = imgui.input_float("fps", ed.path.fps, 1.0, 10.0, "%.1f")
        if changed and v > 0:
            ed.set_timing(fps=v)
        if imgui.button("stop (V)" if ed.previewing else "preview (V)"):
            self.toggle_preview()
        imgui.same_line()
        imgui.set_next_item_width(-1)
        n = ed.num_frames
        changed, f = imgui.slider_int("##pathframe", ed.frame, 0, n - 1, f"frame %d / {n - 1}")
        if changed and ed.keys:
            ed.seek(f)
            self.show_frame(ed.frame)

    def _draw_file(self) -> None:
        imgui = self.app.imgui
        imgui.set_next_item_width(220)
        _, self.file = imgui.input_text("##file", self.file)
        imgui.same_line()
        if imgui.button("save (Ctrl+S)"):
            self.save()
        imgui.set_item_tooltip("render it with: atgs-render CKPT --path FILE.json --out video.mp4")
        imgui.same_line()
        if imgui.button("load"):
            self.load()

    def _draw_overlay(self) -> None:
        """The path as a line and the keyframes as numbered dots, projected into the view."""
        ed = self.editor
        if not ed.keys:
            return
        imgui = self.app.imgui
        if self._overlay is None or self._overlay[0] != ed.revision:
            sp = ed.path.spline()
            t = np.array([k.video_t for k in ed.keys])
            us = np.concatenate([np.linspace(a, b, OVERLAY_SAMPLES, endpoint=False) for a, b in zip(t[:-1], t[1:])]
                                + [t[-1:]])
            self._overlay = (ed.revision, np.stack([sp.eye_at(u) for u in us]))
        io = imgui.get_io()
        fb_w, fb_h = self._framebuffer_size()
        if fb_w <= 0 or fb_h <= 0:
            return
        cam = self.app.control.camera(fb_w, fb_h)
        scale = np.array([io.display_framebuffer_scale.x, io.display_framebuffer_scale.y])
        dl = imgui.get_background_draw_list()
        uv, z = cam.project(self._overlay[1])
        line_col = imgui.IM_COL32(255, 200, 60, 220)
        run: list = []
        for p, zz in zip(uv / scale, z):  # break the line where it passes behind the camera
            if zz > 1e-3 and np.all(np.abs(p) < 1e5):
                run.append((float(p[0]), float(p[1])))
            else:
                if len(run) > 1:
                    dl.add_polyline(run, line_col, 2.0, 0)
                run = []
        if len(run) > 1:
            dl.add_polyline(run, line_col, 2.0, 0)
        eyes = np.stack([k.eye for k in ed.keys])
        # a short tick along each keyframe's viewing direction, scaled to the path's extent
        reach = 0.1 * max(float(np.ptp(self._overlay[1], axis=0).max()), 1e-3)
        tips = eyes + reach * np.stack([k.R[2] for k in ed.keys])
        (kuv, kz), (tuv, tz) = cam.project(eyes), cam.project(tips)
        for i in range(len(ed.keys)):
            p, tip = kuv[i] / scale, tuv[i] / scale
            if kz[i] > 1e-3 and np.all(np.abs(p) < 1e5):
                col = imgui.IM_COL32(80, 220, 255, 255) if i == ed.selected else imgui.IM_COL32(255, 255, 255, 230)
                if tz[i] > 1e-3 and np.all(np.abs(tip) < 1e5):
                    dl.add_line((float(p[0]), float(p[1])), (float(tip[0]), float(tip[1])), col, 2.0)
                dl.add_circle_filled((float(p[0]), float(p[1])), 5.0, col)
                dl.add_text((float(p[0]) + 7, float(p[1]) - 7), col, str(i + 1))
