"""The player's default window size (atgs/viewer/window_size.py)."""

from __future__ import annotations

import pytest

from atgs.viewer.window_size import default_window_size


@pytest.mark.parametrize("camera", [(256, 192), (2704, 2028), (96, 72), (1920, 1080), (4000, 1000), (1000, 4000)])
@pytest.mark.parametrize("screen", [(1280, 800), (1920, 1040), (3840, 2100), (800, 600)])
def test_window_keeps_the_camera_shape_and_fits_the_screen(camera, screen) -> None:
    w, h = default_window_size(camera, screen)
    assert w <= screen[0] and h <= screen[1]
    assert abs(w / h - camera[0] / camera[1]) <= camera[0] / camera[1] / min(w, h) * 1.01  # same shape, to a pixel
    largest_w = min(screen[0], screen[1] * camera[0] / camera[1])  # widest window of that shape on the screen
    if largest_w >= 960:
        assert w >= 960 or w >= 0.8 * largest_w - 1  # at least 960 wide, or already 80% of the screen
    else:
        assert w >= largest_w - 1  # a small screen: as large as it goes
    assert w <= max(960, 0.8 * largest_w) + 1  # not more than 80% of the screen unless needed for 960


def test_small_and_large_cameras_on_a_laptop_screen() -> None:
    assert default_window_size((256, 192), (1280, 800)) == (960, 720)  # >= 960 wide, grown from a thumbnail
    w, h = default_window_size((2704, 2028), (1280, 800))  # a 2.7K camera fits the screen
    assert w <= 1280 and h <= 800 and w >= 960
    assert default_window_size((1920, 1080), (3840, 2100)) == (2986, 1680)  # 80% of the height, 16:9
    assert default_window_size((256, 192), None) == default_window_size((256, 192), (1280, 800))  # no monitor info
