"""The compute-shader decode (atgs/viewer/gl_decode.py) against the torch decode, on llvmpipe.

Every Gaussian the training decode draws (its anchor and slot ids say which) must sit at slot
``position of the anchor in the window x q + slot`` of the GL columns with the same packed values
(float32 round-off; one unit of the 16-bit quantization), and every other slot must have opacity
0 (the torch decode drops them; the sort and the splat shader cull them). The four cases turn on
each step of the decode: plain heads, fade and velocity, smoothing + opacity cut + clearance, the
per-keyframe layout with static keyframe-0 anchors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from builders import DECODE_CASES, DECODE_FRAMES, decode_case_model, side_camera
from atgs.model.precision import low_precision_view
from atgs.viewer.gl_decode import GLDecodeUnavailable, GLFrameDecoder, gl_decode_problem
from atgs.viewer.errors import ViewerError
from atgs.viewer.headless import HeadlessRenderer
from atgs.viewer.packing import pack_gaussians
from atgs.viewer.scene_utils import resized
from atgs.viewer.splat_renderer import RenderSettings

COLUMN_TYPES = ((np.float32, 3), (np.int16, 4), (np.float32, 3), (np.uint16, 4))


@pytest.fixture(scope="module")
def ctx(compute_ctx):
    return compute_ctx  # (tests/conftest.py: fails, not skips, without OpenGL 4.3)


def read_columns(frame) -> list[np.ndarray]:
    n = frame.count
    return [np.frombuffer(buf.read(), dtype=dt)[: n * k].reshape(n, k) for buf, (dt, k) in zip(frame.columns, COLUMN_TYPES)]


def torch_slots(model, f: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """(GL slot of each Gaussian the torch decode draws, its packed columns)."""
    tl = model.timeline
    with torch.no_grad():
        d = model._decode(f, tl.segment_of_frame(f), tl.local_time_of_frame(f), None, track=False)
    window = model.active_anchors(f).nonzero().squeeze(1)
    position = torch.full((model.num_anchors,), -1, dtype=torch.long)
    position[window] = torch.arange(window.numel())
    assert bool((position[d.anchor_ids] >= 0).all())
    slots = (position[d.anchor_ids] * model.cfg.gaussians_per_anchor + d.slot_ids).numpy()
    return slots, [np.asarray(c) for c in pack_gaussians(d.gaussians).columns]


@pytest.mark.parametrize("case", list(DECODE_CASES))
def test_gl_decode_equals_the_torch_decode(ctx, case: str) -> None:
    model = decode_case_model(case)
    decoder = GLFrameDecoder(ctx, model)
    dropped_somewhere = False
    for f in (0, 5, 8, DECODE_FRAMES - 1):
        frame = decoder.decode(f)
        got = read_columns(frame)
        slots, ref = torch_slots(model, f)
        assert frame.count == model.active_anchors(f).sum() * model.cfg.gaussians_per_anchor
        assert len(slots) > 0
        means, quat, scales, oprgb = (g[slots] for g in got)
        np.testing.assert_allclose(means, ref[0], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(scales, ref[2], rtol=1e-5, atol=1e-7)
        assert np.abs(quat.astype(np.int32) - ref[1]).max() <= 1
        assert np.abs(oprgb.astype(np.int32) - ref[3]).max() <= 1
        others = np.ones(frame.count, dtype=bool)
        others[slots] = False
        assert (got[3][others, 0] == 0).all(), "a Gaussian the torch decode drops has opacity in the GL columns"
        dropped_somewhere |= bool(others.any())
    if case != "plain":  # fades, the cut and the clearance drop Gaussians: the test sees them
        assert dropped_somewhere
    decoder.release()


def test_a_hash_table_over_the_gl_limit_is_kept_one_segment_at_a_time(ctx) -> None:
    """A GL whose storage buffers cannot hold the whole table (block_bytes below it): the current
    segment's grid is uploaded when playback reaches it, with the same result; an anchor table
    over the limit is a one-line refusal."""
    model = decode_case_model("motion")
    just_under = 4 * model.hash.table.numel() - 4  # (the anchor table and the MLPs still fit here)
    whole, small = GLFrameDecoder(ctx, model), GLFrameDecoder(ctx, model, block_bytes=just_under)
    assert small._one_grid_at_a_time and not whole._one_grid_at_a_time
    segments = set()
    for f in (0, 8, DECODE_FRAMES - 1, 3):  # through every segment and back
        segments.add(model.timeline.segment_of_frame(f))
        a, b = read_columns(whole.decode(f)), read_columns(small.decode(f))
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)
    assert len(segments) == model.timeline.num_segments > 1
    with pytest.raises(GLDecodeUnavailable, match="anchor table needs"):
        GLFrameDecoder(ctx, model, block_bytes=1024)
    whole.release(), small.release()


def test_frames_alternate_between_buffer_sets(ctx) -> None:
    """Frame t+1 decodes into other buffers than frame t (t may still be drawn), then they repeat."""
    model = decode_case_model("motion")
    decoder = GLFrameDecoder(ctx, model, slots=2)
    a, b, c = decoder.decode(3), decoder.decode(4), decoder.decode(5)
    assert {id(x) for x in a.columns}.isdisjoint(id(x) for x in b.columns)
    assert [id(x) for x in a.columns] == [id(x) for x in c.columns]
    assert not np.array_equal(read_columns(b)[0], read_columns(c)[0])  # frame 5 moved on from 4
    decoder.release()


def test_what_cannot_be_decoded_on_the_gl_says_why(ctx) -> None:
    model = decode_case_model("plain")
    assert gl_decode_problem(ctx, model) is None
    assert "ATGS checkpoints" in gl_decode_problem(ctx, object())
    reduced = low_precision_view(model, torch.bfloat16)
    with pytest.raises(GLDecodeUnavailable, match="decoder"):
        GLFrameDecoder(ctx, reduced)


def _psnr(a: np.ndarray, b: np.ndarray, peak: float) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(peak * peak / mse)


@pytest.mark.parametrize("case", ["motion", "everything"])
def test_a_frame_decoded_and_sorted_on_the_gl_is_the_torch_image(case: str) -> None:
    """HeadlessRenderer with --decode gl (decode, sort and an indirect draw, all on the GL) against
    --decode torch (torch decode, torch sort, the columns uploaded): colour, alpha and depth."""
    model = decode_case_model(case)
    cam = resized(side_camera(), (128, 96))
    images = {}
    for route in ("torch", "gl"):
        hr = HeadlessRenderer(model, "auto", "cpu", route)
        try:
            for f in (2, 9):
                hr.show_frame(f)
                for mode in ("color", "alpha", "depth"):
                    images[route, f, mode] = hr.renderer.render_image(cam, RenderSettings(mode=mode))
                images[route, f, "drawn"] = hr.renderer.drawn_count()
                images[route, f, "range"] = hr.renderer.depth_range
        finally:
            hr.close()
    for f in (2, 9):
        assert images["gl", f, "drawn"] == images["torch", f, "drawn"] > 0
        assert images["torch", f, "alpha"].max() > 0.3  # the view sees the Gaussians
        assert _psnr(images["gl", f, "color"], images["torch", f, "color"], 1.0) > 60
        assert _psnr(images["gl", f, "alpha"], images["torch", f, "alpha"], 1.0) > 60
        depth = images["torch", f, "depth"]
        assert _psnr(images["gl", f, "depth"], depth, float(depth.max())) > 60
        np.testing.assert_allclose(images["gl", f, "range"], images["torch", f, "range"], rtol=1e-5)


def test_decode_gl_refuses_what_it_cannot_decode_in_one_line(tmp_path) -> None:
    from atgs.viewer.loading import load_source

    with pytest.raises(ViewerError, match="--decode gl: only ATGS checkpoints"):
        HeadlessRenderer(load_source("demo", 500, None), "auto", "cpu", "gl")


def test_the_gl_route_holds_the_training_rasterizer_to_45_db() -> None:
    """The issue's bound for any change to the player: the headless image of a frame decoded,
    sorted and drawn on the GL against atgs.render on the torch decode of that frame."""
    from atgs.render import rasterize_gaussians

    model = decode_case_model("everything")
    cam = resized(side_camera(), (128, 96))
    f = 9
    ref = rasterize_gaussians(model.gaussians_at_frame(f), cam, torch.zeros(3), backend="torch", near=model.near).image
    hr = HeadlessRenderer(model, "auto", "cpu", "gl")
    try:
        hr.show_frame(f)
        img = hr.renderer.render_image(cam, RenderSettings())
    finally:
        hr.close()
    assert float(ref.max()) > 0.2
    assert _psnr(img, ref.detach().numpy(), 1.0) > 45
