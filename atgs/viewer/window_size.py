"""The player window's default size: as large as is comfortable on the screen, in the camera's shape.

The window takes the opening camera's aspect ratio (not a fixed 16:9): the training view fills
the window without bars, and a camera path saved from the player renders by default at the
window's size, i.e. in the shape of the training cameras. It is the largest such size within
``SCREEN_SHARE`` of the monitor's work area; if that is narrower than ``MIN_WIDTH`` it grows to
``MIN_WIDTH`` as far as the work area allows, so that small training images (256x192) do not
play in a thumbnail. Splats are rendered at the window's resolution (with adaptive resolution
while moving), so a window larger than the training images costs only render time.
"""

from __future__ import annotations

SCREEN_SHARE = 0.8
MIN_WIDTH = 960
FALLBACK_SCREEN = (1280, 800)  # when the monitor's work area cannot be read
MIN_SIDE = 64


def default_window_size(camera: tuple[int, int], screen: tuple[int, int] | None) -> tuple[int, int]:
    """Window (width, height) for a camera of size ``camera`` on a work area of size ``screen``."""
    cam_w, cam_h = camera
    scr_w, scr_h = screen if screen and screen[0] > 0 and screen[1] > 0 else FALLBACK_SCREEN
    aspect = cam_w / cam_h
    width = min(SCREEN_SHARE * scr_w, SCREEN_SHARE * scr_h * aspect)
    if width < MIN_WIDTH:
        width = min(float(MIN_WIDTH), scr_w, scr_h * aspect)  # never beyond the work area itself
    width = int(width)  # rounding down keeps it inside the bounds above
    height = min(int(round(width * cam_h / cam_w)), int(scr_h))
    return max(MIN_SIDE, width), max(MIN_SIDE, height)


def screen_work_area(glfw) -> tuple[int, int] | None:
    """(width, height) of the primary monitor's work area (screen minus task bars), or None."""
    try:
        monitor = glfw.get_primary_monitor()
        if not monitor:
            return None
        _, _, w, h = glfw.get_monitor_workarea(monitor)
    except Exception:  # an unusual display server must not keep the player from opening
        return None
    return (int(w), int(h)) if w > 0 and h > 0 else None
