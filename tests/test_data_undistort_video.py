"""Undistortion against a slow reference (fixed-point inversion of the distortion model) and
video round trips through PyAV."""

from __future__ import annotations

import numpy as np
import pytest

from atgs.cameras import Camera, look_at
from atgs.data.errors import DataError
from layouts import write_colmap_frames_layout, write_easyvolcap_layout
from atgs.data.prepare import PrepareConfig, prepare
from atgs.data.scene import PreparedScene
from atgs.data.undistort import apply_undistort_map, build_undistort_map, undistort_points_reference
from atgs.data.video import iter_frames, video_info
from atgs.io.video import VideoWriter

W, H = 96, 72


def _pattern(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Smooth analytic image of undistorted pixel coordinates (bilinear resampling is ~exact)."""
    return np.stack([128 + 100 * np.sin(u / 9.0), 128 + 100 * np.cos(v / 7.0), 128 + 60 * np.sin((u + v) / 13.0)], -1)


def _distorted_camera() -> Camera:
    K = np.array([[80.0, 0, 47.0], [0, 82.0, 37.5], [0, 0, 1]])
    return Camera("cam00", W, H, K, look_at(np.array([3.0, 0, 1]), np.zeros(3)), np.array([-0.12, 0.03, 0.002, -0.001, 0]))


def _distorted_image(cam: Camera) -> np.ndarray:
    """What the distorted lens records: each distorted pixel shows the pattern at its undistorted position."""
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    und = undistort_points_reference(np.stack([u.ravel(), v.ravel()], -1), cam)
    return _pattern(und[:, 0], und[:, 1]).reshape(H, W, 3)


def test_undistort_matches_reference() -> None:
    cam = _distorted_camera()
    m = build_undistort_map(cam)
    out = apply_undistort_map(m, _distorted_image(cam).astype(np.float32))
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    want = _pattern(u, v)
    inner = (slice(6, H - 6), slice(6, W - 6))  # border pixels map outside the source
    err = np.abs(out[inner] - want[inner])
    assert err.max() < 2.5 and err.mean() < 0.5, (err.max(), err.mean())
    # the reference really inverts the forward model used by Camera.project
    X = np.array([[0.2, 0.3, -0.1], [0.0, -0.4, 0.5]])
    uv_d, _ = cam.project(X)
    uv_u, _ = Camera("p", W, H, cam.K, cam.w2c).project(X)
    np.testing.assert_allclose(undistort_points_reference(uv_d, cam), uv_u, atol=1e-8)


@pytest.mark.parametrize("layout", ["easyvolcap", "colmap-frames"])
def test_prepare_undistorts_distorted_input(tmp_path, layout) -> None:
    cam = _distorted_camera()
    img = np.clip(np.round(_distorted_image(cam)), 0, 255).astype(np.uint8)
    cam2 = Camera("cam01", W, H, cam.K, look_at(np.array([3.0, 1.0, 1]), np.zeros(3)), cam.dist)
    write = write_easyvolcap_layout if layout == "easyvolcap" else write_colmap_frames_layout
    write(tmp_path / "src", [cam, cam2], lambda ci, f: img, 2)
    s = PreparedScene.load(prepare(PrepareConfig(src=tmp_path / "src", out=tmp_path / "p", keyframes=1, progress=False)))
    assert s.source["format"] == layout
    assert all(c.dist is None for c in s.cameras)
    np.testing.assert_allclose(s.cameras[0].K, cam.K)
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    err = np.abs(s.image(0, 1) * 255 - _pattern(u, v))[6:-6, 6:-6]
    assert err.mean() < 1.0, err.mean()


@pytest.mark.parametrize("codec, crf, pix_fmt, min_psnr", [("libx264rgb", 0, None, np.inf), ("libx264", 10, "yuv444p", 35.0)])
def test_video_round_trip(tmp_path, codec, crf, pix_fmt, min_psnr) -> None:
    rng = np.random.default_rng(0)
    u, v = np.meshgrid(np.arange(64), np.arange(48))
    frames = [np.clip(_pattern(u + 3 * f, v) + rng.normal(0, 3, (48, 64, 3)), 0, 255).astype(np.uint8) for f in range(5)]
    path = tmp_path / "v.mp4"
    with VideoWriter(path, 64, 48, 25, codec, crf, pix_fmt) as w:
        for f in frames:
            w.write(f)
    assert video_info(path) == (5, 64, 48, 25.0)
    assert video_info(path, exact=True)[0] == 5
    got = dict(iter_frames(path))
    mse = np.mean([(got[i].astype(float) - frames[i]) ** 2 for i in range(5)])
    psnr = np.inf if mse == 0 else 10 * np.log10(255 ** 2 / mse)
    assert psnr >= min_psnr
    assert [i for i, _ in iter_frames(path, 1, 5, 2)] == [1, 3]


def _numbered_video(path, n: int, gop: int, fps: float = 25.0):
    """A lossless video whose frame i shows i in binary (8 blocks of 8 px, white = 1)."""
    frames = []
    with VideoWriter(path, 64, 16, fps) as w:
        w.stream.codec_context.gop_size = gop
        for i in range(n):
            img = np.zeros((16, 64, 3), np.uint8)
            for b in range(7):
                img[:, 8 * b : 8 * b + 8] = 255 * ((i >> b) & 1)
            img[:, 56:] = (3 * i) % 256
            frames.append(img)
            w.write(img)
    return frames


def test_iter_frames_seeks_to_a_far_start_and_yields_the_same_frames(tmp_path) -> None:
    from fractions import Fraction

    import av

    from atgs.data.video import SEEK_MIN_FRAMES, _frames_after_seek, _open

    path = tmp_path / "numbered.mp4"
    frames = _numbered_video(path, 120, gop=10)
    for start, end, step in ((SEEK_MIN_FRAMES, 40, 1), (77, 90, 1), (95, None, 3), (119, 120, 1), (60, 61, 1)):
        got = list(iter_frames(path, start, end, step))
        want = list(range(start, 120 if end is None else end, step))
        assert [i for i, _ in got] == want
        for i, img in got:
            np.testing.assert_array_equal(img, frames[i], err_msg=f"frame {i} (start {start})")
    # it did seek: the first frame decoded after seeking to 77 is a keyframe after frame 0
    with _open(path) as c:
        it = _frames_after_seek(c, path, 77)
        assert it is not None and 0 < next(it)[0] <= 77
    # variable frame rate (a gap of ~4 frame times after frame 20): indices still count frames
    odd = tmp_path / "vfr.mp4"
    c = av.open(str(odd), mode="w")
    st = c.add_stream("libx264rgb", rate=25)
    st.width, st.height, st.pix_fmt = 64, 16, "rgb24"
    st.codec_context.time_base = Fraction(1, 1000)
    st.options = {"crf": "0", "g": "10"}
    for i in range(60):
        fr = av.VideoFrame.from_ndarray(np.full((16, 64, 3), (5 * i) % 256, np.uint8), format="rgb24")
        fr.pts, fr.time_base = 40 * i + (150 if i >= 20 else 0), Fraction(1, 1000)  # a gap after frame 20
        for pkt in st.encode(fr):
            c.mux(pkt)
    for pkt in st.encode():
        c.mux(pkt)
    c.close()
    linear = {i: img for i, img in enumerate(im for _, im in iter_frames(odd))}
    got = list(iter_frames(odd, 45, 50))
    assert [i for i, _ in got] == [45, 46, 47, 48, 49]
    for i, img in got:
        np.testing.assert_array_equal(img, linear[i])
    with _open(odd) as c:
        it = _frames_after_seek(c, odd, 45)
        assert it is not None and 20 < next(it)[0] <= 45  # seeked past the gap


def test_video_errors_name_the_file(tmp_path) -> None:
    with pytest.raises(DataError, match=r"missing.mp4: video not found"):
        video_info(tmp_path / "missing.mp4")
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"garbage" * 50)
    with pytest.raises(DataError, match=r"bad.mp4: cannot open video"):
        video_info(bad)
