"""The model stream (``atgs-export --format web --web-stream model``): the part files read back
to the model's tensors at each precision (the plain reference reader), and the page's own WebGL2
decode (read back from its textures in headless Chromium) against the torch decode."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from atgs.web.export import export_web
from atgs.web.model_format import PartFormatError, read_part
from atgs.web.model_stream import anchor_groups, anchor_tensors, read_model_stream
from builders import decode_case_model

# a float16 value is within 2^-11 of the float32 (relative), plus the smallest normal's step
F16_REL, F16_ABS = 2.0**-11, 2.0**-24


@pytest.fixture(scope="module")
def model():
    """Every decode step at work: dense and hashed levels, 3 segments, fade, velocity, the 3D
    filter, the clearance and the opacity cut, anchors outside the grid box."""
    return decode_case_model("everything")


def _export(model, folder: Path, precision: str) -> Path:
    return _export_frames(model, folder, list(range(model.num_frames)), precision)


def _export_frames(model, folder: Path, frames: list[int], precision: str = "float16") -> Path:
    export_web(model, folder, frames, stream="model", precision=precision, progress=False)
    return folder / "stream"


@pytest.fixture(scope="module")
def streams(model, tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("model-stream")
    return {p: _export(model, root / p, p) for p in ("float32", "float16", "int8")}


def _parts_by_name(files) -> dict[str, dict]:
    return {p["file"]: t for p, t in zip(files.manifest["model"]["parts"], files.parts)}


@pytest.mark.parametrize("precision", ["float32", "float16", "int8"])
def test_the_parts_read_back_to_the_models_tensors(model, streams, precision):
    files = read_model_stream(streams[precision])
    parts = _parts_by_name(files)
    w = parts["weights.bin"]
    for name in ("tmlp_w1", "tmlp_b1", "tmlp_w2", "tmlp_b2"):  # the MLPs are always float32
        assert np.array_equal(w[name], getattr(model, name).numpy()), name
    assert np.array_equal(w["offset.w1"], model.decoder.offset[0].weight.detach().numpy())
    assert np.array_equal(w["centres"], model.clearance.centres.numpy())
    box = (model.bbox_max - model.bbox_min).numpy()
    for k, ids in anchor_groups(model):
        got = parts["anchors_static.bin" if k < 0 else f"anchors_kf_{k:04d}.bin"]
        want = anchor_tensors(model, ids)
        assert set(got) == set(want)
        for name, x in want.items():
            y = got[name]
            if precision == "float32":
                assert np.array_equal(y, x), name
            elif name == "mu":  # 16 bits over the anchors' own range, within the model's box
                assert np.abs(y - x).max() <= box.max() / 65535, name
            elif precision == "float16":
                assert np.all(np.abs(y - x) <= F16_REL * np.abs(x) + F16_ABS), name
            else:  # int8: half a step of the column's scale
                step = np.abs(x.reshape(len(x), -1)).max(0) / 127
                assert np.all(np.abs(y - x).reshape(len(x), -1) <= 0.5 * step + 1e-7), name
    hg = model.hash
    per = hg.levels * hg.table_size
    for m in range(model.num_segments):
        x = hg.table[m * per:(m + 1) * per].numpy().reshape(hg.levels, hg.table_size, -1)
        y = parts[f"hash_seg_{m:04d}.bin"]["hash"].reshape(x.shape)
        if precision == "float32":
            tol = np.zeros_like(x)
        elif precision == "float16":
            tol = F16_REL * np.abs(x) + F16_ABS
        else:  # int8: half a step of each level's and feature's scale
            tol = np.broadcast_to(0.5 * np.abs(x).max(1, keepdims=True) / 127 + 1e-7, x.shape)
        assert np.all(np.abs(y - x) <= tol), m


def test_each_frame_lists_the_parts_of_its_keyframe_window(model, streams):
    files = read_model_stream(streams["float16"])
    man = files.manifest["model"]
    parts = man["parts"]
    for i, f in enumerate(files.manifest["frames"]):
        entry = man["frames"][i]
        ids = torch.cat([ids for k, ids in anchor_groups(model) if any(parts[p]["keyframe"] == k for p in entry["anchors"])])
        assert torch.equal(ids.sort().values, model.active_anchors(f).nonzero().squeeze(1))
        assert parts[entry["hash"]]["segment"] == model.timeline.segment_of_frame(f)


def test_an_export_of_a_few_frames_ships_their_windows_only(model, tmp_path):
    frames = [0, 1]
    files = read_model_stream(_export_frames(model, tmp_path / "web", frames))
    parts = files.manifest["model"]["parts"]
    needed = {k for f in frames for k in model.anchor_keyframe[model.active_anchors(f)].unique().tolist()}
    assert {p["keyframe"] for p in parts if p["kind"] == "anchors"} == needed
    assert {p["segment"] for p in parts if p["kind"] == "hash"} == {model.timeline.segment_of_frame(f) for f in frames}
    assert len(needed) < len(anchor_groups(model))


def test_float16_takes_half_the_bytes_of_float32_and_int8_less(streams):
    size = {p: sum(q["bytes"] for q in json.loads((s / "manifest.json").read_text())["model"]["parts"])
            for p, s in streams.items()}
    assert size["float16"] < 0.7 * size["float32"] and size["int8"] < size["float16"]


def test_a_corrupt_part_is_one_clear_error(streams, tmp_path):
    data = (streams["float16"] / "weights.bin").read_bytes()
    with pytest.raises(PartFormatError, match="weights.bin: not a complete gzip stream"):
        read_part(data[: len(data) // 2], "weights.bin")


# --- the page's decode ---------------------------------------------------------------------------------


def _torch_frame(model, f: int):
    """Frame f by the training decode, with each Gaussian's (anchor, slot)."""
    with torch.no_grad():
        d = model.decode_frame(f, None, track=False)
    g = d.gaussians
    return d.anchor_ids.numpy(), d.slot_ids.numpy(), g


@pytest.fixture(scope="module")
def browser():
    from atgs.web.browser import chromium

    with chromium() as b:
        yield b


def test_the_page_decodes_what_torch_decodes(model, streams, browser):
    _check_page_decode(model, streams["float32"], browser)


def test_the_page_decodes_the_per_keyframe_layout(browser, tmp_path):
    """Static anchors of keyframe 0 in every window (static_keyframe0), the 3D filter."""
    model = decode_case_model("per-keyframe")
    _check_page_decode(model, _export(model, tmp_path / "web", "float32"), browser)


def test_the_page_decodes_sizes_that_are_not_multiples_of_four(browser, tmp_path):
    """Padding of every vec4 layout: 3 hash levels (6 features), D = 6, hidden layers of 10 and
    7 units, 3 Gaussians an anchor."""
    from atgs.model.config import HashGridConfig
    from builders import random_point_model, ring_cameras, tiny_config

    cfg = tiny_config(K=3, W=3, M=2, hidden=10, feature_dim=6, gaussians_per_anchor=3, hidden_offset=7,
                      hash=HashGridConfig(levels=3, features_per_level=2, log2_table_size=8, base_resolution=4,
                                          mlp_hidden=10))
    model = random_point_model(cfg, 9, 60, ring_cameras(3, (32, 24)), randomize=True)
    _check_page_decode(model, _export(model, tmp_path / "web", "float32"), browser)


def _check_page_decode(model, stream: Path, browser) -> None:
    from atgs.web.browser import PlayerPage, serving

    folder = stream.parent
    files = read_model_stream(stream)
    man = files.manifest["model"]
    ids_of_keyframe = dict(anchor_groups(model))
    ids_of_part = {i: ids_of_keyframe[p["keyframe"]] for i, p in enumerate(man["parts"]) if p["kind"] == "anchors"}
    q = model.cfg.gaussians_per_anchor
    kf = model.timeline.keyframe_frames()
    frames = [kf[1], kf[1] + 1, kf[2] - 1, kf[2]]  # across a keyframe and a window change
    with serving(folder) as url:
        page = PlayerPage(browser, url, {"paused": 1, "size": "camera"})
        page.first_frame()
        for f in frames:
            got = page.call(f"await p.gaussians({f})")
            order = torch.cat([ids_of_part[p] for p in got["anchors"]]).numpy()
            n = got["count"]
            assert n == order.size * q
            field = {k: np.asarray(got[k], np.float32).reshape(n, 4) for k in ("mean", "quat", "scale", "color")}
            kept = field["mean"][:, 3] > 0
            assert kept.any(), f"frame {f}: nothing kept"
            slot_anchor, slot_j = np.repeat(order, q), np.tile(np.arange(q), order.size)
            anchors, slots, g = _torch_frame(model, f)
            want = {(int(a), int(j)): i for i, (a, j) in enumerate(zip(anchors, slots))}
            page_keys = [(int(a), int(j)) for a, j in zip(slot_anchor[kept], slot_j[kept])]
            assert sorted(page_keys) == sorted(want), f"frame {f}: the page keeps other Gaussians than torch"
            at = np.array([want[k] for k in page_keys])
            for name, got_x, want_x in (("means", field["mean"][kept, :3], g.means), ("opacities", field["mean"][kept, 3], g.opacities),
                                        ("quats", field["quat"][kept], g.quats), ("scales", field["scale"][kept, :3], g.scales),
                                        ("colors", field["color"][kept, :3], g.colors)):
                ref = want_x.numpy()[at]
                err = np.abs(got_x - ref).max()
                assert err <= 1e-4 * max(1.0, float(np.abs(ref).max())), (f, name, err)
        page.close()


def test_a_missing_part_is_an_error_on_the_page(streams, browser, tmp_path):
    import shutil

    from atgs.web.browser import PlayerPage, serving

    broken = tmp_path / "broken"
    shutil.copytree(streams["float16"].parent, broken)
    man = json.loads((broken / "stream" / "manifest.json").read_text())["model"]
    last = man["parts"][man["frames"][-1]["hash"]]["file"]
    assert man["frames"][0]["hash"] != man["frames"][-1]["hash"]
    (broken / "stream" / last).unlink()
    with serving(broken) as url:
        page = PlayerPage(browser, url, {"paused": 1})
        page.first_frame()  # frame 0 needs another segment's grid: it still shows
        page.page.evaluate(f"() => {{ window.atgsPlayer.seek({len(man['frames']) - 1}); }}")
        text = page.error_text()
        assert last in text and "missing" in text
        page.close()


NODE_READER = """
import { readFileSync } from 'node:fs';
import { gunzipSync } from 'node:zlib';
import { parsePart } from './atgs/web/player/model_part.js';
const out = {};
for (const [name, t] of Object.entries(parsePart(new Uint8Array(gunzipSync(readFileSync(process.argv[2]))), 'x'))) {
  out[name] = { shape: t.shape, data: Buffer.from(t.data.buffer).toString('base64') };
}
console.log(JSON.stringify(out));
"""


@pytest.mark.parametrize("precision", ["float16", "int8"])
def test_the_pages_reader_reads_what_the_reference_reader_reads(streams, precision, tmp_path):
    import base64
    import shutil
    import subprocess

    root = Path(__file__).resolve().parents[1]
    script = root / f".model_part_reader_{precision}.mjs"  # next to atgs/ so that its import resolves
    script.write_text(NODE_READER)
    try:
        for name in ("anchors_static.bin", "hash_seg_0001.bin"):
            path = streams[precision] / name
            run = subprocess.run([shutil.which("node"), str(script), str(path)], capture_output=True, text=True,
                                 timeout=60, cwd=root)
            assert run.returncode == 0, run.stderr
            got = json.loads(run.stdout)
            want = read_part(path.read_bytes())
            assert set(got) == set(want)
            for k, t in got.items():
                x = np.frombuffer(base64.b64decode(t["data"]), np.float32).reshape(t["shape"])
                assert np.array_equal(x, want[k]), (name, k)  # bit for bit
    finally:
        script.unlink()
