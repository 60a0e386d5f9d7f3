"""Image files of every common PIL mode read as (H, W, 3) uint8 RGB (atgs.io.images), against
values computed by hand; PIL's own convert("RGB") clips 16-bit greyscale to white."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from atgs.data.sources import load_image
from atgs.io.images import read_rgb8, to_rgb8


def test_16_bit_greyscale_png_is_scaled_not_clipped(tmp_path: Path) -> None:
    values = np.array([[0, 257, 32896], [65535, 1000, 60000]], dtype=np.uint16)
    path = tmp_path / "g16.png"
    Image.fromarray(values).save(path)
    with Image.open(path) as im:
        assert im.mode.startswith("I")  # what PIL makes of a 16-bit PNG
        clipped = np.asarray(im.convert("RGB"))[..., 0]  # the clipping this module avoids
        np.testing.assert_array_equal(clipped, np.minimum(values, 255))
    got = read_rgb8(path)
    want = np.rint(values / 257.0).astype(np.uint8)
    assert got.shape == (2, 3, 3) and got.dtype == np.uint8
    for c in range(3):
        np.testing.assert_array_equal(got[..., c], want)


def test_transparent_pixels_are_composited_over_black(tmp_path: Path) -> None:
    rgba = np.zeros((2, 2, 4), dtype=np.uint8)
    rgba[..., :3] = [200, 100, 50]
    rgba[..., 3] = [[255, 0], [128, 64]]
    path = tmp_path / "a.png"
    Image.fromarray(rgba, "RGBA").save(path)
    got = load_image(path)
    want = np.rint(np.array([200, 100, 50], dtype=np.float64)[None, None] * rgba[..., 3:] / 255.0)
    np.testing.assert_array_equal(got, want.astype(np.uint8))
    assert got[0, 1].tolist() == [0, 0, 0]  # fully transparent: black, not the stored colour


def test_opaque_alpha_and_plain_modes_keep_their_colours() -> None:
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (5, 7, 3), dtype=np.uint8)
    opaque = np.concatenate([rgb, np.full((5, 7, 1), 255, np.uint8)], axis=2)
    np.testing.assert_array_equal(to_rgb8(Image.fromarray(opaque, "RGBA")), rgb)
    np.testing.assert_array_equal(to_rgb8(Image.fromarray(rgb, "RGB")), rgb)
    grey = rgb[..., 0]
    np.testing.assert_array_equal(to_rgb8(Image.fromarray(grey, "L")), np.repeat(grey[..., None], 3, axis=2))


def test_palette_with_transparency_and_float_images() -> None:
    pal = Image.new("P", (2, 1))
    pal.putpalette([10, 20, 30, 200, 150, 100] + [0] * 762)
    pal.putpixel((0, 0), 0)
    pal.putpixel((1, 0), 1)
    pal.info["transparency"] = 0  # palette entry 0 fully transparent
    assert to_rgb8(pal).tolist() == [[[0, 0, 0], [200, 150, 100]]]
    unit = Image.fromarray(np.array([[0.0, 0.5, 1.0]], dtype=np.float32), "F")
    assert to_rgb8(unit)[0, :, 0].tolist() == [0, 128, 255]
    wide = Image.fromarray(np.array([[0.0, 127.6, 300.0]], dtype=np.float32), "F")
    assert to_rgb8(wide)[0, :, 1].tolist() == [0, 128, 255]
