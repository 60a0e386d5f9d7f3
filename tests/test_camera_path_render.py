"""Camera path files: save/load, clear errors (exit 2), and `atgs-render --path FILE.json`
against frames rendered one by one at the same cameras."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from atgs.cameras import look_at
from atgs.viewer.camera_path import CameraPath, PathKey
from atgs.viewer.camera_path_file import load_camera_path, path_to_json, save_camera_path
from atgs.viewer.cli import main as view_main
from atgs.viewer.cli import render_main
from atgs.viewer.errors import ViewerError
from builders import write_tiny_checkpoint

RENDER = "import sys; from atgs.viewer.cli import render_main; sys.exit(render_main(sys.argv[1:]))"


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tiny_checkpoint(tmp_path_factory.mktemp("paths") / "ckpt.pt", num_frames=9)


def sample_path(size: tuple[int, int] | None = (64, 48)) -> CameraPath:
    """Three keyframes around the tiny checkpoint's scene, scene time running 0 -> 1."""
    keys = []
    for i, (a, h) in enumerate(((0.0, 1.0), (1.2, 0.4), (2.5, 1.5))):
        eye = np.array([3.2 * math.cos(a), 3.2 * math.sin(a), h])
        keys.append(PathKey(i / 2, look_at(eye, np.zeros(3), np.array([0, 0, 1.0])), 45.0 + 5 * i, i / 2))
    return CameraPath(keys, duration_s=0.6, fps=10.0, size=size)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) / 255 - b.astype(np.float64) / 255) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(1.0 / mse)


def test_saved_path_loads_back_identical(tmp_path: Path) -> None:
    for size in ((64, 48), None):
        path = sample_path(size)
        path.keys[1].w2c[:3, 3] += 1e-13  # digits beyond what a short float format would keep
        f = save_camera_path(path, tmp_path / "sub" / "p.json")
        data = json.loads(f.read_text())
        assert data["format"] == "atgs-camera-path" and data["version"] == 1
        back = load_camera_path(f)
        assert (back.duration_s, back.fps, back.size) == (path.duration_s, path.fps, path.size)
        assert len(back.keys) == len(path.keys)
        for a, b in zip(path.keys, back.keys):
            assert (a.video_t, a.scene_t, a.fov_y_deg) == (b.video_t, b.scene_t, b.fov_y_deg)
            np.testing.assert_array_equal(a.w2c, b.w2c)
        assert path_to_json(back) == f.read_text()
    with pytest.raises(ViewerError, match="no keyframes"):
        save_camera_path(CameraPath(), tmp_path / "empty.json")


def _variants(good: dict) -> dict[str, str]:
    """Broken files (name -> text) and a word the one-line error must contain."""
    def edit(fn) -> str:
        d = json.loads(json.dumps(good))
        fn(d)
        return json.dumps(d)

    return {
        "empty": "",
        "blank": "  \n",
        "truncated": json.dumps(good)[:-40],
        "notapath": json.dumps({"hello": 1}),
        "nokeys": edit(lambda d: d.update(keyframes=[])),
        "newer": edit(lambda d: d.update(version=2)),
        "order": edit(lambda d: d["keyframes"][2].update(video_t=0.25)),
        "shape": edit(lambda d: d["keyframes"][1].update(w2c=[[1, 0, 0], [0, 1, 0], [0, 0, 1]])),
        "rotation": edit(lambda d: d["keyframes"][0]["w2c"][0].__setitem__(0, 3.0)),
        "fov": edit(lambda d: d["keyframes"][0].update(fov_y_deg=0)),
        "fps": edit(lambda d: d.update(fps="fast")),
    }


NEEDLES = {"empty": "empty", "blank": "empty", "truncated": "JSON", "notapath": "atgs-camera-path",
           "nokeys": "no keyframes", "newer": "version 2", "order": "video order", "shape": "4x4",
           "rotation": "rotation", "fov": "fov_y_deg", "fps": "fps"}


def test_malformed_or_empty_path_file_is_one_line_and_exit_2(ckpt: Path, tmp_path: Path, capsys) -> None:
    good = json.loads(path_to_json(sample_path()))
    out = tmp_path / "keep.mp4"
    out.write_bytes(b"an earlier video")
    for name, text in _variants(good).items():
        f = tmp_path / f"{name}.json"
        f.write_text(text)
        assert render_main([str(ckpt), "--path", str(f), "--out", str(out)]) == 2, name
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and str(f) in err and NEEDLES[name] in err and "Traceback" not in err, (name, err)
    for arg, needle in (("missing.json", "not found"), ("spiral", "expected orbit, cameras")):
        assert render_main([str(ckpt), "--path", str(tmp_path / arg) if arg.endswith("json") else arg,
                            "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and needle in err, err
    assert out.read_bytes() == b"an earlier video"  # failed runs never touch the output
    # the player refuses a broken --path file before it opens a window
    assert view_main([str(ckpt), "--path", str(tmp_path / "truncated.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("atgs-view: error:") and "truncated.json" in err and err.count("\n") == 0
    # the real command line, as a user runs it: exit code 2 and one line on stderr
    proc = subprocess.run([sys.executable, "-c", RENDER, str(ckpt), "--path", str(tmp_path / "empty.json"),
                           "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    err = proc.stderr.strip()
    assert err == f"atgs-render: error: {tmp_path / 'empty.json'}: empty file, not a camera path; save one from the player (atgs-view)"


def test_path_render_matches_frames_rendered_one_by_one(ckpt: Path, tmp_path: Path) -> None:
    """atgs-render --path (decode-ahead pipeline, PNG frames) equals each frame rendered alone
    at the path's camera and sequence frame, from a fresh decode."""
    from atgs.viewer.headless import HeadlessRenderer
    from atgs.viewer.loading import load_source
    from atgs.timeline import frame_at
    from atgs.viewer.splat_renderer import RenderSettings

    path = sample_path(size=(64, 48))
    f = save_camera_path(path, tmp_path / "path.json")
    out = tmp_path / "frames"
    assert render_main([str(ckpt), "--path", str(f), "--out", str(out), "--gl", "osmesa"]) == 0
    files = sorted(out.iterdir())
    assert [p.name for p in files] == [f"{i:05d}.png" for i in range(6)]  # 0.6 s at 10 fps
    source = load_source(ckpt)
    n, F = 6, source.num_frames
    hr = HeadlessRenderer(source, "osmesa")
    seq_frames, psnrs = [], []
    try:
        for i, file in enumerate(files):
            pose = path.pose_at(i / (n - 1))
            seq_frames.append(frame_at(pose.scene_t, F))
            ref = hr.frame_rgb8(seq_frames[-1], pose.camera(64, 48), RenderSettings())
            img = np.asarray(Image.open(file))
            assert img.shape == (48, 64, 3) and ref.std() > 1.0
            psnrs.append(_psnr(img, ref))
            assert psnrs[-1] >= 50.0, i
    finally:
        hr.close()
    assert seq_frames[0] == 0 and seq_frames[-1] == F - 1 and len(set(seq_frames)) >= 4  # time plays along


def test_path_render_defaults_and_overrides(ckpt: Path, tmp_path: Path) -> None:
    import av

    f = save_camera_path(sample_path(size=(33, 25)), tmp_path / "path.json")
    out = tmp_path / "v.mp4"
    assert render_main([str(ckpt), "--path", str(f), "--out", str(out), "--fps", "5"]) == 0
    with av.open(str(out)) as c:
        frames = [fr.to_ndarray(format="rgb24") for fr in c.decode(video=0)]
        rate = c.streams.video[0].average_rate
    assert len(frames) == 3 and frames[0].shape == (24, 32, 3)  # 0.6 s at 5 fps; the file's size made even
    assert float(rate) == pytest.approx(5.0)
    frames_dir = tmp_path / "frames"
    assert render_main([str(ckpt), "--path", str(f), "--out", str(frames_dir), "--frames", "2", "--size", "20x16"]) == 0
    assert len(list(frames_dir.iterdir())) == 2
    assert render_main([str(ckpt), "--path", str(f), "--out", str(frames_dir), "--frames", "3"]) == 0  # re-render
    assert len(list(frames_dir.iterdir())) == 3
    (frames_dir / "notes.txt").write_text("mine")  # a directory with other files is never replaced
    assert render_main([str(ckpt), "--path", str(f), "--out", str(frames_dir)]) == 2
    assert (frames_dir / "notes.txt").read_text() == "mine"
