"""Training and loading on a device: ``atgs-train --device``, ``atgs.load(device=)``,
``ATGSModel.to``, resume across devices. The CUDA tests need a GPU and gsplat and skip without
them; the device-agnostic code they run is the code the CPU tests run (and
tests/test_device_placement.py checks it creates nothing off the model's device)."""

from __future__ import annotations

import json
import math

import pytest
import torch

import atgs
from atgs.device import DeviceError, resolve_device
from atgs.render.cuda import gsplat_available
from atgs.train.config import preset
from atgs.train.trainer import Trainer
from builders import growing_tiny_config, make_toy_scene, write_tiny_checkpoint

needs_cuda = pytest.mark.skipif(not gsplat_available(), reason="needs a CUDA device and gsplat (pip install gsplat)")
needs_cuda_device = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (torch sees none)")


@pytest.fixture(scope="module")
def scene():
    return make_toy_scene(num_frames=5, num_cameras=4, width=32, height=24, keyframes=3)


def _model_tensors(obj, seen=None):
    """Every tensor an ATGS model holds (its own, its grids', its decoder's), found by walking
    the attributes of the atgs objects it is made of (so a table added later is not missed)."""
    seen = set() if seen is None else seen
    if id(obj) in seen:
        return
    seen.add(id(obj))
    if isinstance(obj, torch.nn.Module):
        yield from obj.parameters()
        yield from obj.buffers()
        return
    for name, value in vars(obj).items():
        if name == "inference_cache":
            continue
        if isinstance(value, torch.Tensor):
            yield value
        elif isinstance(value, torch.nn.Module) or type(value).__module__.startswith("atgs.model"):
            yield from _model_tensors(value, seen)


# --- choosing the device --------------------------------------------------------------------------

def test_device_rule(monkeypatch) -> None:
    import atgs.render.cuda as cuda

    assert resolve_device("cpu", need_gsplat=True) == torch.device("cpu")
    with pytest.raises(DeviceError, match="--device gpu: choose one of auto, cpu, cuda"):
        resolve_device("gpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto", need_gsplat=True).type == "cpu"
    with pytest.raises(DeviceError, match="no CUDA device .* or use --device cpu"):
        resolve_device("cuda")
    # a GPU but no gsplat: training cannot use it, playback can
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(cuda, "gsplat_import_error", lambda: "ModuleNotFoundError: No module named 'gsplat'")
    assert resolve_device("auto", need_gsplat=True).type == "cpu"
    assert resolve_device("cuda", need_gsplat=False).type == "cuda"
    with pytest.raises(DeviceError, match="No module named 'gsplat'.*pip install gsplat .*nvcc.*, or use --device cpu"):
        resolve_device("cuda", need_gsplat=True)
    monkeypatch.setattr(cuda, "gsplat_import_error", lambda: None)
    assert resolve_device("auto", need_gsplat=True).type == "cuda"


@pytest.mark.parametrize(("backend_module", "expected"), [
    ("_C = None", "gsplat found no CUDA compiler (nvcc) to build its kernels"),  # gsplat's own fallback
    ("raise RuntimeError(\"Error building extension 'gsplat_cuda'\\nnvcc fatal\")",
     "RuntimeError: Error building extension 'gsplat_cuda'"),
    ("_C = object()", None),
])
def test_gsplat_counts_as_usable_only_with_its_kernels(backend_module, expected, tmp_path, monkeypatch) -> None:
    """gsplat from PyPI builds its CUDA kernels when they are first loaded; without nvcc it still
    imports (and every call fails later with a NoneType error). A stand-in package checks each case."""
    import sys

    import atgs.render.cuda as cuda

    pkg = tmp_path / "gsplat"
    (pkg / "cuda").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "cuda" / "__init__.py").write_text("")
    (pkg / "cuda" / "_backend.py").write_text(backend_module + "\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    for name in ("gsplat", "gsplat.cuda", "gsplat.cuda._backend"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    cuda.gsplat_import_error.cache_clear()
    try:
        assert cuda.gsplat_import_error() == expected
    finally:
        cuda.gsplat_import_error.cache_clear()
        for name in ("gsplat", "gsplat.cuda", "gsplat.cuda._backend"):
            sys.modules.pop(name, None)


@pytest.mark.parametrize("missing", ["cuda", "gsplat"])
def test_train_device_cuda_without_it_is_one_line_and_exit_2(missing, toy_scene_dir, tmp_path, capsys,
                                                            monkeypatch) -> None:
    import atgs.render.cuda as cuda
    from atgs.cli.train import main as train_main

    monkeypatch.setattr(torch.cuda, "is_available", lambda: missing != "cuda")
    monkeypatch.setattr(cuda, "gsplat_import_error", lambda: "ModuleNotFoundError: No module named 'gsplat'")
    out = tmp_path / "run"
    assert train_main(["--data", str(toy_scene_dir), "--out", str(out), "tiny", "--device", "cuda",
                       "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    fix = "install a CUDA build of torch, or use --device cpu" if missing == "cuda" else "pip install gsplat"
    assert err.startswith("atgs-train: error: --device cuda: ") and fix in err and "\n" not in err, err
    assert not out.exists(), "nothing is written"


def test_auto_on_a_gpu_machine_without_gsplat_says_why_it_trains_on_the_cpu(toy_scene_dir, tmp_path, capsys,
                                                                          monkeypatch) -> None:
    import atgs.render.cuda as cuda
    from atgs.cli.train import main as train_main

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(cuda, "gsplat_import_error", lambda: "gsplat found no CUDA compiler (nvcc) to build its kernels")
    assert train_main(["--data", str(toy_scene_dir), "--out", str(tmp_path / "run"), "tiny",
                       "--train.iterations", "2", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert ("atgs-train: a CUDA device is present, but this runs on the CPU: gsplat, the GPU rasterizer, is not "
            "usable (gsplat found no CUDA compiler (nvcc) to build its kernels); see docs/gpu.md") in out
    assert json.loads((tmp_path / "run" / "config.json").read_text())["device"] == "cpu"
    # with gsplat usable, auto takes the GPU and there is nothing to explain
    from atgs.device import auto_fallback_note
    monkeypatch.setattr(cuda, "gsplat_import_error", lambda: None)
    assert auto_fallback_note("auto", torch.device("cuda"), need_gsplat=True) is None
    assert auto_fallback_note("cpu", torch.device("cpu"), need_gsplat=True) is None


def test_train_backend_that_cannot_rasterize_on_the_device_is_refused(scene, tmp_path) -> None:
    m, t = preset("tiny")
    t.render_backend = "cuda"
    with pytest.raises(DeviceError, match="--train.render-backend cuda needs CUDA tensors"):
        Trainer(scene, m, t, tmp_path)


def test_train_with_device_cpu_end_to_end(toy_scene_dir, tmp_path, capsys) -> None:
    from atgs.cli.train import main as train_main

    out = tmp_path / "run"
    assert train_main(["--data", str(toy_scene_dir), "--out", str(out), "tiny", "--train.iterations", "6",
                       "--device", "cpu", "--no-progress"]) == 0
    assert "on cpu" in capsys.readouterr().out
    assert json.loads((out / "config.json").read_text())["device"] == "cpu"
    assert json.loads((out / "result.json").read_text())["steps"] == 6
    model = atgs.load(out / "ckpt.pt", device="cpu")
    assert model.device.type == "cpu" and len(model.gaussians_at_frame(3)) > 0
    # --resume takes --device too (the run was started with another one on a GPU machine)
    assert train_main(["--data", str(toy_scene_dir), "--out", str(out), "--resume", "--train.iterations", "8",
                       "--device", "cpu", "--no-progress"]) == 0
    assert json.loads((out / "result.json").read_text())["steps"] == 2


# --- checkpoints and moving models ---------------------------------------------------------------------

def test_checkpoints_hold_cpu_tensors_and_load_where_asked(scene, tmp_path, monkeypatch) -> None:
    from atgs.checkpoint import on_cpu

    tr = Trainer(scene, *growing_tiny_config(6), tmp_path)
    tr.train(progress=False, final_renders=False)
    data = torch.load(tmp_path / "ckpt.pt", weights_only=True)  # no map_location: as written
    tensors = [v for v in _leaves(data) if isinstance(v, torch.Tensor)]
    assert len(tensors) > 50 and all(t.device.type == "cpu" for t in tensors)
    nested = {"a": [torch.ones(2), (torch.zeros(1), 3)], "b": "x"}
    moved = on_cpu(nested)
    assert moved["a"][0] is nested["a"][0] and isinstance(moved["a"][1], tuple) and moved["b"] == "x"

    model = atgs.load(tmp_path / "ckpt.pt", device=torch.device("cpu"))
    for f in range(scene.num_frames):
        for x, y in zip(model.gaussians_at_frame(f).as_tuple(), tr.model.gaussians_at_frame(f).as_tuple()):
            assert torch.equal(x, y)
    on_meta = atgs.load(tmp_path / "ckpt.pt", device="meta")  # any device: every tensor goes there
    assert {t.device.type for t in _model_tensors(on_meta)} == {"meta"}
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(DeviceError, match="torch sees no CUDA device.*load with device='cpu'"):
        atgs.load(tmp_path / "ckpt.pt", device="cuda")
    with pytest.raises(DeviceError, match="not a torch device"):
        atgs.load(tmp_path / "ckpt.pt", device="gpu")


def _leaves(tree):
    if isinstance(tree, dict):
        for v in tree.values():
            yield from _leaves(v)
    elif isinstance(tree, (list, tuple)):
        for v in tree:
            yield from _leaves(v)
    else:
        yield tree


def test_model_to_moves_every_tensor_and_empties_the_decode_cache(tmp_path) -> None:
    from atgs.viewer.device import place_source

    model = atgs.load(write_tiny_checkpoint(tmp_path / "ckpt.pt"))
    tensors = list(_model_tensors(model))
    assert len(tensors) >= 20 and {t.device.type for t in tensors} == {"cpu"}
    before = model.gaussians_at_frame(4)
    assert model.to("cpu") is model and model.inference_cache._features is not None, "same device: nothing moves"
    again = model.gaussians_at_frame(4)
    assert all(torch.equal(x, y) for x, y in zip(before.as_tuple(), again.as_tuple()))
    # the viewer's place_source uses to(): the model it returns decodes on the device
    moved = place_source(model, torch.device("meta"))
    assert moved is model and model.device.type == "meta"
    assert {t.device.type for t in _model_tensors(model)} == {"meta"}
    assert model.inference_cache._features is None, "no cached tensor is left on the old device"


# --- on a GPU (skipped without CUDA and gsplat) -------------------------------------------------------

@needs_cuda
def test_cuda_training_steps_are_finite_and_densification_grows_anchors(scene, tmp_path) -> None:
    tr = Trainer(scene, *growing_tiny_config(10), tmp_path, device="cuda")
    anchors = tr.model.num_anchors
    results = [tr.train_step() for _ in range(10)]
    assert all(not r.skipped and math.isfinite(r.loss) for r in results)
    assert tr.model.device.type == "cuda" and tr.stats.device.type == "cuda"
    assert tr.model.num_anchors > anchors, "densification grew anchors from gsplat's screen-space gradients"


@needs_cuda_device  # trained on the CPU: no gsplat needed
def test_cpu_and_cuda_decode_of_a_checkpoint_agree(scene, tmp_path) -> None:
    tr = Trainer(scene, *growing_tiny_config(8), tmp_path)
    tr.train(progress=False, final_renders=False)
    cpu = atgs.load(tmp_path / "ckpt.pt", device="cpu")
    gpu = atgs.load(tmp_path / "ckpt.pt", device="cuda")
    for model in (cpu, gpu):
        model.cfg.opacity_threshold = 0.0  # the same Gaussians on both (none near the cut drops out)
    for f in range(scene.num_frames):
        a, b = cpu.gaussians_at_frame(f), gpu.gaussians_at_frame(f)
        assert b.means.device.type == "cuda"
        for x, y in zip(a.as_tuple(), b.as_tuple()):
            torch.testing.assert_close(y.cpu(), x, rtol=1e-4, atol=1e-5)


@needs_cuda
@pytest.mark.parametrize(("first", "then"), [("cuda", "cpu"), ("cpu", "cuda")])
def test_resume_across_devices(first, then, scene, tmp_path) -> None:
    tr = Trainer(scene, *growing_tiny_config(12), tmp_path, device=first)
    tr.run_steps(progress=False, stop_at=6)
    resumed = Trainer.resume(scene, tmp_path / "ckpt.pt", tmp_path, device=then)
    assert resumed.step == 6 and resumed.model.num_anchors == tr.model.num_anchors
    for name, table in resumed.model.sparse_tensors().items():
        assert table.device.type == then and resumed.sparse_opt.exp_avg[name].device.type == then
        torch.testing.assert_close(resumed.sparse_opt.exp_avg[name].cpu(), tr.sparse_opt.exp_avg[name].cpu(),
                                   rtol=0, atol=0)
    dense = [s["exp_avg"] for s in resumed.dense_opt.state.values()]
    assert dense and all(x.device.type == then for x in dense)
    result = resumed.run_steps(progress=False)
    assert result["steps"] == 6 and resumed.skipped == 0
    assert all(torch.isfinite(t).all() for t in resumed.model.sparse_tensors().values())
