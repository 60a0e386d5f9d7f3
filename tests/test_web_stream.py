"""The Python half of the web export (docs/web.md): the chunk layout written by
atgs.web.stream_format against its reference reader and error bounds computed here, the exported
folder against the checkpoint it came from, and atgs-serve."""

from __future__ import annotations

import gzip
import json
import math
import os
import re
import signal
import socket
import struct
import subprocess
import sys
import threading
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

import atgs
from atgs.cli.export import main as export_main
from atgs.cli.serve import main as serve_main
from atgs.errors import OutputError
from atgs.gaussians import Gaussians
from atgs.render import rasterize_gaussians
from atgs.render.environment import EnvironmentMap
from atgs.web.export import export_web, frame_with_ids
from atgs.web.server import make_server
from atgs.web.stream_format import (HEADER, MAGIC, ChunkFormatError, StreamFrame, decode_chunk, encode_chunk,
                                    pack_chunk, quantize_chunk)
from builders import train_tiny_checkpoint
from test_cli_promises import _default_sigint

EPS = 1e-6


def _frame(ids, means, scales=None, quats=None, opacities=None, colors=None) -> StreamFrame:
    n = len(ids)
    return StreamFrame(np.asarray(ids, np.int64), np.asarray(means, np.float64).reshape(n, 3),
                       np.full((n, 3), 0.1) if scales is None else np.asarray(scales, np.float64),
                       np.tile([1.0, 0, 0, 0], (n, 1)) if quats is None else np.asarray(quats, np.float64),
                       np.full(n, 0.5) if opacities is None else np.asarray(opacities, np.float64),
                       np.full((n, 3), 0.25) if colors is None else np.asarray(colors, np.float64))


def _random_frames(rng: np.random.Generator, F: int = 5, pool: int = 60) -> list[StreamFrame]:
    frames = []
    for _ in range(F):
        ids = rng.choice(pool, size=int(rng.integers(pool // 2, pool)), replace=False)
        n = ids.size
        frames.append(_frame(ids, rng.normal(size=(n, 3)) * [1.0, 3.0, 0.2], np.exp(rng.uniform(-7, 0, (n, 3))),
                             rng.normal(size=(n, 4)), rng.random(n), rng.uniform(-0.1, 1.1, (n, 3))))
    return frames


# --- the chunk layout ----------------------------------------------------------------------------------


def test_round_trip_stays_within_the_quantization_steps() -> None:
    rng = np.random.default_rng(0)
    frames = _random_frames(rng)
    chunk = quantize_chunk(frames)
    data = encode_chunk(frames)
    assert data == pack_chunk(chunk) and data[:2] == b"\x1f\x8b"
    back = decode_chunk(data)
    ids = chunk.ids
    assert back.gaussians == ids.size == np.unique(np.concatenate([f.ids for f in frames])).size
    # the ranges and steps, from the inputs alone
    means = np.concatenate([f.means for f in frames])
    log_s = np.log(np.concatenate([f.scales for f in frames]))
    lo, hi = means.min(0), means.max(0)
    assert np.allclose(back.position_min, lo, atol=EPS) and np.allclose(back.position_max, hi, atol=EPS)
    pos_step = (hi - lo) / 65535
    ls_step = (log_s.max() - log_s.min()) / 255
    for fr, got in zip(frames, back.frames):
        at = {int(i): k for k, i in enumerate(ids)}
        rows = np.array([at[int(i)] for i in fr.ids])
        assert np.all(np.abs(got.means[rows] - fr.means) <= pos_step / 2 + EPS)
        assert np.all(np.abs(np.log(got.scales[rows]) - np.log(fr.scales)) <= ls_step / 2 + EPS)
        unit = fr.quats / np.linalg.norm(fr.quats, axis=1, keepdims=True)
        unit *= np.where(unit[:, :1] < 0, -1, 1)
        assert np.all(got.quats[rows, 0] >= 0) and np.all(np.abs(got.quats[rows] - unit) <= 0.5 / 127 + EPS)
        assert np.all(np.abs(got.opacities[rows] - fr.opacities) <= 0.5 / 255 + EPS)
        assert np.all(np.abs(got.colors[rows] - np.clip(fr.colors, 0, 1)) <= 0.5 / 255 + EPS)
        absent = np.setdiff1d(np.arange(ids.size), rows)
        assert absent.size and np.all(got.opacities[absent] == 0)  # absent: drawn with opacity 0


def test_absent_gaussians_take_the_nearest_present_frame() -> None:
    fixed = [_frame([0, 1], [[0, 0, 0], [10, 10, 10]])]  # spans the position range
    frames = [_frame([0, 1, 7], [[0, 0, 0], [10, 10, 10], [1, 1, 1]]), fixed[0], fixed[0], fixed[0],
              _frame([0, 1, 7], [[0, 0, 0], [10, 10, 10], [9, 9, 9]])]
    back = decode_chunk(encode_chunk(frames))
    row = 2  # id 7: dynamic, after the two static ones
    assert back.static == 2
    got = [fr.records.position[row, 0] for fr in back.frames]
    assert got == [6554, 6554, 6554, 58982, 58982]  # frame 2: equally near both, takes the earlier
    assert [int(fr.records.opacity[row, 0]) for fr in back.frames] == [128, 0, 0, 0, 128]


def test_static_means_same_record_in_every_frame_and_comes_first_by_id() -> None:
    base = np.array([[0.0, 0, 0], [1, 1, 1], [0.4, 0.4, 0.4], [0.25, 0.25, 0.25], [0.75, 0.75, 0.75]])
    ids = [40, 10, 30, 20, 50]
    frames = []
    for k in range(4):
        m = base.copy()
        m[2] += 1e-9 * k  # id 30: changes far below a position step (1/65535)
        m[3, 0] += 0.01 * k  # id 20: moves
        keep = [0, 1, 2, 3] if k == 2 else [0, 1, 2, 3, 4]  # id 50: constant but absent once
        frames.append(_frame([ids[i] for i in keep], m[keep]))
    chunk = quantize_chunk(frames)
    assert chunk.static == 3 and chunk.ids.tolist() == [10, 30, 40, 20, 50]
    back = decode_chunk(encode_chunk(frames))
    assert (back.gaussians, back.static) == (5, 3)
    assert decode_chunk(encode_chunk(frames[:1])).static == 5  # one frame: nothing changes
    colour = [frames[0]] + [_frame(ids, base, colors=np.full((5, 3), 0.25 + 0.01 * k)) for k in (1, 2)]
    assert quantize_chunk(colour).static == 0  # any field counts


def test_frame_blocks_are_byte_plane_deltas_modulo_256() -> None:
    """One dynamic Gaussian between two static corners (positions are their own u16 steps), its
    bytes checked in the inflated stream where docs/web.md puts them."""
    corners = [[0, 0, 0], [65535, 65535, 65535]]
    q0, q1 = [0.6, -0.8, 0, 0], [0.6, 0.8, 0, 0]
    frames = [_frame([1, 2, 5], corners + [[255, 511, 65535]], quats=[[1, 0, 0, 0]] * 2 + [q0]),
              _frame([1, 2, 5], corners + [[256, 256, 0]], quats=[[1, 0, 0, 0]] * 2 + [q1])]
    data = encode_chunk(frames)
    raw = gzip.decompress(data)
    magic, version, F, G, S = struct.unpack_from("<4sHHII", raw)
    assert (magic, version, F, G, S) == (MAGIC, 1, 2, 3, 2) and len(raw) == 48 + 17 * (2 + 2 * 1)
    block0, block1 = raw[48 + 34:48 + 51], raw[48 + 51:]
    # planes: x lo, x hi, y lo, y hi, z lo, z hi, 3 log-scales, w x y z, opacity, r g b
    assert list(block0[:6]) == [255, 0, 255, 1, 255, 255] and list(block0[9:13]) == [76, 256 - 102, 0, 0]
    assert list(block1) == [1, 1, 1, 0, 1, 1] + [0] * 3 + [0, 204, 0, 0] + [0] * 4
    back = decode_chunk(data)
    assert back.frames[1].records.position[2].tolist() == [256, 256, 0]
    assert back.frames[1].records.rotation[2].tolist() == [76, 102, 0, 0]
    np.testing.assert_allclose(back.frames[1].means[2], [256, 256, 0], atol=1e-3)


def test_degenerate_ranges_do_not_divide_by_zero() -> None:
    frames = [_frame([3, 4], [[1, 2, 3], [1, 2, 3]], scales=np.full((2, 3), 0.2), quats=np.zeros((2, 4)))] * 2
    with np.errstate(all="raise"):
        back = decode_chunk(encode_chunk(frames))
    fr = back.frames[1]
    assert np.allclose(fr.means, [1, 2, 3]) and np.allclose(fr.scales, 0.2)
    assert fr.quats.tolist() == [[1, 0, 0, 0]] * 2  # no rotation: the identity
    empty = decode_chunk(encode_chunk([_frame([], np.zeros((0, 3)))]))
    assert empty.gaussians == 0 and empty.frames[0].means.shape == (0, 3)


def test_reader_errors_name_what_is_wrong() -> None:
    raw = gzip.decompress(encode_chunk(_random_frames(np.random.default_rng(1), F=2, pool=8)))
    G = struct.unpack_from("<I", raw, 8)[0]
    cases = [
        (b"XXXX" + raw[4:], "bad magic"),
        (raw[:4] + struct.pack("<H", 2) + raw[6:], "version 2"),
        (raw[:40], "truncated header"),
        (raw[:-3], "truncated"),
        (raw + b"\0", "trailing bytes"),
        (raw[:12] + struct.pack("<I", G + 1) + raw[16:], "S <= G"),
    ]
    for bad, needle in cases:
        with pytest.raises(ChunkFormatError, match=needle):
            decode_chunk(gzip.compress(bad, mtime=0))
    whole = gzip.compress(raw, mtime=0)
    for bad in (whole[: len(whole) // 2], b"not gzip at all"):
        with pytest.raises(ValueError, match="gzip"):
            decode_chunk(bad)


# --- the export against the checkpoint -----------------------------------------------------------------


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return train_tiny_checkpoint(tmp_path_factory.mktemp("web") / "run")


@pytest.fixture(scope="module")
def model(ckpt: Path):
    return atgs.load(ckpt)


@pytest.fixture(scope="module")
def exported(ckpt: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("exported") / "web"
    assert export_main([str(ckpt), "--out", str(out), "--format", "web", "--web-stream", "gaussians", "--chunk-frames",
                        "4", "--no-progress"]) == 0
    return out


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return 10 * math.log10(1.0 / max(float(((a - b) ** 2).mean()), 1e-20))


def test_the_decode_with_ids_is_the_inference_decode(model) -> None:
    for f in range(model.num_frames):
        fr, g = frame_with_ids(model, f), model.gaussians_at_frame(f)
        assert np.unique(fr.ids).size == len(fr.ids) == len(g)
        for got, want in zip((fr.means, fr.quats, fr.scales, fr.opacities, fr.colors), g.as_tuple()):
            np.testing.assert_allclose(got, want.numpy(), rtol=1e-5, atol=2e-6)


def test_the_export_is_a_complete_folder_that_decodes_to_the_model(ckpt: Path, model, exported: Path, capsys) -> None:
    man = json.loads((exported / "stream" / "manifest.json").read_text())
    assert man["format"] == "atgs-web" and man["version"] == 1 and man["fps"] == model.fps
    assert man["frames"] == list(range(6)) and man["chunk_frames"] == 4
    assert [(c["file"], c["frames"]) for c in man["chunks"]] == [("chunk_000000.bin", 4), ("chunk_000001.bin", 2)]
    assert sorted(p.name for p in (exported / "stream").iterdir()) == ["chunk_000000.bin", "chunk_000001.bin",
                                                                       "manifest.json"]
    assert [c["name"] for c in man["cameras"] if c["held_out"]] == model.test_camera_names == ["cam03"]
    cam = man["cameras"][0]
    assert cam["w2c"] == model.cameras[0].w2c.reshape(-1).tolist() and cam["fx"] == model.cameras[0].fx
    assert man["background"] == list(model.background) and man["environment"] is None
    assert model.near > 0.01  # the model's own near plane (atgs.model.near_plane), not the default
    assert man["render"] == {"near": model.near, "dilation": 0.3, "alpha_min": 1 / 255, "alpha_max": 0.99, "extent": 3.0,
                          "clamp_margin": 0.3}
    assert len(man["scene"]["center"]) == 3 and man["scene"]["radius"] > 0
    assert man["source"] == {"checkpoint": str(ckpt.resolve()), "step": 30}
    shipped = Path(atgs.__file__).parent / "web" / "player"
    assert sorted(p.name for p in (exported / "player").iterdir()) == sorted(
        p.name for p in shipped.iterdir() if p.suffix in (".js", ".css"))
    assert (exported / "index.html").is_file() == (shipped / "index.html").is_file()

    cam = next(c for c in model.cameras if c.name not in model.test_camera_names)
    bg = torch.tensor(model.background)
    worst = math.inf
    for i, entry in enumerate(man["chunks"]):
        data = (exported / "stream" / entry["file"]).read_bytes()
        assert entry["bytes"] == len(data)
        back = decode_chunk(data)
        assert (back.gaussians, back.static, len(back.frames)) == (entry["gaussians"], entry["static"], entry["frames"])
        for k, fr in enumerate(back.frames):
            want = model.gaussians_at_frame(man["frames"][4 * i + k])
            assert int((fr.opacities > 0).sum()) == len(want)
            got = Gaussians(*(torch.from_numpy(a) for a in (fr.means, fr.quats, fr.scales, fr.opacities, fr.colors)))
            a, b = rasterize_gaussians(want, cam, bg).image, rasterize_gaussians(got, cam, bg).image
            assert float(a.std()) > 0.02
            worst = min(worst, _psnr(a, b))
    assert worst > 40.0, worst


def test_the_summary_line_and_the_bad_arguments(ckpt: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "web"
    gaussians = ["--format", "web", "--web-stream", "gaussians"]
    assert export_main([str(ckpt), "--out", str(out), *gaussians, "--frames", "0:6:3", "--no-progress"]) == 0
    line = capsys.readouterr().out.strip()
    assert re.fullmatch(r"atgs-export: wrote 2 frames \(\d+ Gaussians per frame\) in 1 chunk to .*: [\d,]+ bytes, "
                        r"[\d,]+ B per frame, \d+\.\d\d B per Gaussian-frame; serve it with: atgs-serve .*", line), line
    before = sorted(p.relative_to(out) for p in out.rglob("*"))
    for argv, needle in ((["--chunk-frames", "0"], "--chunk-frames 0: must be within 1..65535"),
                         (["--chunk-frames", "65536"], "--chunk-frames 65536"),
                         ([], "--overwrite")):
        assert export_main([str(ckpt), "--out", str(out), *gaussians, "--no-progress", *argv]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("atgs-export: error: ") and needle in err and "\n" not in err, err
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == before  # refused: untouched


def test_the_model_streams_summary_line_and_bad_arguments(ckpt: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "web"
    model_stream = ["--format", "web"]  # the default stream
    assert export_main([str(ckpt), "--out", str(out), *model_stream, "--no-progress"]) == 0
    line = capsys.readouterr().out.strip()
    assert re.fullmatch(r"atgs-export: wrote the model for 6 frames in \d+ part files to .*: [\d,]+ bytes, "
                        r"[\d,]+ B per frame; serve it with: atgs-serve .*", line), line
    man = json.loads((out / "stream" / "manifest.json").read_text())
    assert man["kind"] == "model" and man["model"]["precision"] == "int8" and "chunks" not in man
    argv = [str(ckpt), "--out", str(out), *model_stream, "--no-progress", "--overwrite"]
    assert export_main([*argv, "--min-opacity", "0.1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "atgs-export: error: --min-opacity applies to --web-stream gaussians only (the model stream drops " \
                  "what the model's own opacity cut drops)", err
    with pytest.raises(SystemExit) as exit_:  # the argument parser's own refusal of an unknown precision
        export_main([*argv, "--web-precision", "int4"])
    assert exit_.value.code == 2 and "int4" in capsys.readouterr().err


def test_a_failed_export_leaves_nothing(model, tmp_path: Path, monkeypatch) -> None:
    import atgs.web.export as web_export

    real = web_export.pack_chunk

    def second_fails(chunk):
        if second_fails.calls:
            raise OSError(28, "No space left on device")
        second_fails.calls += 1
        return real(chunk)

    second_fails.calls = 0
    monkeypatch.setattr(web_export, "pack_chunk", second_fails)
    with pytest.raises(OutputError, match="No space left on device"):
        export_web(model, tmp_path / "web", [0, 1, 2], stream="gaussians", chunk_frames=2, progress=False)
    assert list(tmp_path.iterdir()) == []


def test_environment_and_min_opacity(model, tmp_path: Path, monkeypatch) -> None:
    texels = torch.rand(4, 8, 3, generator=torch.Generator().manual_seed(0))
    basis = np.array([[0.0, 1, 0], [-1, 0, 0], [0, 0, 1]])
    monkeypatch.setattr(model, "environment", EnvironmentMap(texels, basis))
    opac = model.gaussians_at_frame(1).opacities.sort().values
    cut = float(opac[len(opac) // 2: len(opac) // 2 + 2].mean())  # between two: no tie with round-off
    res = export_web(model, tmp_path / "web", [1], stream="gaussians", min_opacity=cut, progress=False)
    assert 0 < res.gaussians[0] == int((model.gaussians_at_frame(1).opacities >= cut).sum()) < len(model.gaussians_at_frame(1))
    man = json.loads((tmp_path / "web" / "stream" / "manifest.json").read_text())
    assert man["environment"] == {"file": "environment.png", "basis": basis.reshape(-1).tolist()}
    png = np.asarray(Image.open(tmp_path / "web" / "stream" / "environment.png"))
    assert png.shape == (4, 8, 3) and np.array_equal(png, (texels * 255).round().to(torch.uint8).numpy())


# --- atgs-serve ----------------------------------------------------------------------------------------


@pytest.fixture
def site(tmp_path: Path) -> Path:
    """A web export's shape, by hand (the player's own files are another engineer's)."""
    out = tmp_path / "site"
    (out / "stream").mkdir(parents=True)
    (out / "player").mkdir()
    (out / "index.html").write_text("<!doctype html><title>atgs</title>")
    (out / "player" / "stream.js").write_text("export const x = 1;\n")
    (out / "stream" / "manifest.json").write_text('{"format": "atgs-web"}')
    (out / "stream" / "chunk_000000.bin").write_bytes(encode_chunk(_random_frames(np.random.default_rng(2), 2, 8)))
    return out


def _get(url: str) -> tuple[bytes, str]:
    with urllib.request.urlopen(url, timeout=10) as r:
        return r.read(), r.headers["Content-Type"]


def test_the_server_serves_the_files_as_they_are(site: Path) -> None:
    server = make_server(site, "127.0.0.1", 0)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        base = f"http://127.0.0.1:{server.server_address[1]}/"
        for name, mime in (("index.html", "text/html"), ("player/stream.js", "text/javascript"),
                           ("stream/manifest.json", "application/json"),
                           ("stream/chunk_000000.bin", "application/octet-stream")):
            body, ctype = _get(base + name)
            assert body == (site / name).read_bytes() and ctype.split(";")[0] == mime, name
    finally:
        server.shutdown()
        server.server_close()


def test_atgs_serve_prints_its_address_and_serves(site: Path) -> None:
    proc = subprocess.Popen([sys.executable, "-m", "atgs.cli.serve", str(site), "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_default_sigint)
    try:
        line = proc.stdout.readline().strip()
        m = re.fullmatch(r"atgs-serve: serving (.*) at (http://127\.0\.0\.1:(\d+)/index\.html) \(Ctrl-C to stop\)", line)
        assert m and m.group(1) == str(site) and int(m.group(3)) > 0, (line, proc.stderr.read() if not m else "")
        assert _get(m.group(2))[0] == (site / "index.html").read_bytes()
        chunk = m.group(2).replace("index.html", "stream/chunk_000000.bin")
        assert _get(chunk)[0] == (site / "stream" / "chunk_000000.bin").read_bytes()
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=20)
    assert proc.returncode == 130 and err.strip() == "atgs-serve: interrupted"


def test_atgs_serve_errors_are_one_line(site: Path, tmp_path: Path, capsys) -> None:
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    port = busy.getsockname()[1]
    (tmp_path / "plain").mkdir()
    try:
        cases = [([str(tmp_path / "missing")], "not found"),
                 ([str(tmp_path / "plain")], "not a web export (no index.html and stream/manifest.json); write one "
                                             "with: atgs-export CKPT --out DIR --format web"),
                 ([str(site), "--port", str(port)], f"port {port} is in use; pick another with --port"),
                 ([str(site), "--port", "70000"], "--port 70000: must be within 0..65535")]
        for argv, needle in cases:
            assert serve_main(argv) == 2, argv
            err = capsys.readouterr().err.strip()
            assert err.startswith("atgs-serve: error: ") and needle in err and "\n" not in err, err
    finally:
        busy.close()
    assert os.listdir(tmp_path / "plain") == []
