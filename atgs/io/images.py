"""Image files of any PIL mode as the (H, W, 3) uint8 RGB arrays the pipeline works in."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

# PIL modes of one integer channel wider than 8 bits (16-bit PNG and TIFF greyscale)
_WIDE_INT_MODES = ("I;16", "I;16L", "I;16B", "I;16N", "I")


def to_rgb8(im: Image.Image) -> np.ndarray:
    """(H, W, 3) uint8 of ``im``.

    PIL's own ``convert("RGB")`` clips 16-bit greyscale to 255 (a white image) and drops an alpha
    channel, keeping whatever colour transparent pixels store. Here 16-bit values are scaled to 8
    bits, float images are read as [0, 1] (or [0, 255] when they exceed 1), and images with
    transparency are composited over black (the trainer then sees a uniform border colour and
    keeps it as the background: docs/training.md)."""
    if im.mode in _WIDE_INT_MODES:
        a = np.asarray(im, dtype=np.float64)
        a = np.clip(np.rint(a / 257.0), 0, 255) if im.mode != "I" or a.max() > 255 else a
        return np.repeat(a.astype(np.uint8)[..., None], 3, axis=2)
    if im.mode == "F":
        a = np.asarray(im, dtype=np.float64)
        a = np.clip(a * 255.0 if np.nanmax(a) <= 1.0 else a, 0, 255)
        return np.repeat(np.rint(np.nan_to_num(a)).astype(np.uint8)[..., None], 3, axis=2)
    if im.mode in ("RGBA", "LA", "PA") or (im.mode == "P" and "transparency" in im.info):
        rgba = im.convert("RGBA")
        if rgba.getchannel("A").getextrema()[0] == 255:  # opaque after all: no float copy
            return np.asarray(rgba.convert("RGB"))
        a = np.asarray(rgba, dtype=np.float32)
        return np.rint(a[..., :3] * (a[..., 3:] / 255.0)).astype(np.uint8)
    return np.asarray(im.convert("RGB"))


def read_rgb8(path: str | Path) -> np.ndarray:
    """(H, W, 3) uint8 of an image file (:func:`to_rgb8`); PIL's errors propagate."""
    with Image.open(path) as im:
        return to_rgb8(im)
