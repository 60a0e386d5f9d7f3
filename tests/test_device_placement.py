"""Guards against device mixing, checked on a CPU-only machine (what would break on CUDA).

On a GPU machine a tensor created without ``device=`` lands on the CPU (torch's default device)
while the model lives on the GPU, and the first op that mixes them fails, or silently copies
every step. Two checks find such tensors here:

- dynamic: the trainer's real step, densification, checkpoint and evaluation run with torch's
  default device set to ``meta``. The model is on the CPU, so any tensor created without an
  explicit device now lands on another device than the model's, exactly as on CUDA, and the
  first op that mixes them raises;
- static: every tensor factory call in the modules training and decoding run through passes
  ``device=`` (``torch.from_numpy`` must be followed by ``.to(...)``), so code paths the dynamic
  run does not reach (other presets, layouts, options) are covered too.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
import torch

from atgs.train.trainer import Trainer
from builders import growing_tiny_config, make_toy_scene

REPO = Path(__file__).resolve().parent.parent

# torch functions that create a tensor on the default device unless given ``device=``
FACTORIES = {"zeros", "ones", "full", "empty", "arange", "tensor", "rand", "randn", "randint", "randperm",
             "linspace", "logspace", "eye", "as_tensor", "asarray", "scalar_tensor"}
# the modules a training step, densification, checkpoints, evaluation and the decode run through
DEVICE_MODULES = [*sorted((REPO / "atgs" / "model").glob("*.py")), *sorted((REPO / "atgs" / "train").glob("*.py")),
                  *(REPO / "atgs" / p for p in ("render/api.py", "render/validate.py", "render/cuda.py",
                                                "render/projection.py", "render/reference.py", "eval/evaluate.py",
                                                "eval/metrics.py", "checkpoint.py", "device.py"))]


def _densifying_config(iterations: int):
    m, t = growing_tiny_config(iterations)
    t.random_background, t.grad_clip, t.eval_max_frames = True, 0.05, 2  # their paths run too
    t.drop_gaussians = 0.2
    return m, t


def test_training_creates_no_tensor_off_the_model_device(tmp_path) -> None:
    scene = make_toy_scene(num_frames=5, num_cameras=4, width=32, height=24, keyframes=3)
    m, t = _densifying_config(12)
    # the model is built outside: nn.Linear has no device argument here, so under the check its
    # weights would land on meta (a CUDA run builds it on the CPU, torch's default, and moves it)
    model = Trainer(scene, m, t, tmp_path / "init").model
    anchors = model.num_anchors
    with torch.device("meta"):
        tr = Trainer(scene, m, t, tmp_path, model=model)
    # torch.optim.Adam creates its step counters on the default device by design (host
    # scalars): its first step runs outside the check
    tr.train_step()
    with torch.device("meta"):
        results = [tr.train_step() for _ in range(t.iterations - 1)]
        tr.save()
        ev = tr.evaluate()
        g = tr.model.gaussians_at_frame(2)
    assert all(not r.skipped for r in results) and all(r.loss == r.loss for r in results)
    assert tr.model.num_anchors > anchors, "densification ran under the check"
    assert ev["views"] == 2 and 0 < ev["psnr"] < 100
    assert len(g) > 0 and g.means.device.type == "cpu"
    state = torch.load(tmp_path / "ckpt.pt", weights_only=True)
    assert state["model"]["anchor_feature"].device.type == "cpu" and state["step"] == t.iterations


def test_the_check_catches_a_tensor_created_without_a_device(tmp_path, monkeypatch) -> None:
    """The dynamic check fails on the mistake it is meant to find (a stand-in for a regression)."""
    import atgs.train.densify as densify

    scene = make_toy_scene(num_frames=5, num_cameras=4, width=32, height=24, keyframes=3)
    # the CPU check: with device "auto" a GPU machine trains on CUDA, where the planted mistake
    # did not raise (NVIDIA H200, torch 2.11, 2026-11-27)
    tr = Trainer(scene, *_densifying_config(4), tmp_path, device="cpu")
    tr.train_step()
    real = densify.DensifyStats.record

    def record_without_device(self, dec, *args):  # noqa: ANN001, ANN002, ANN202
        self.anchor_count.index_add_(0, dec.active, torch.ones(dec.active.numel()))  # no device=
        return real(self, dec, *args)

    monkeypatch.setattr(densify.DensifyStats, "record", record_without_device)
    with torch.device("meta"), pytest.raises((RuntimeError, NotImplementedError)):
        tr.train_step()


def _factory_calls_without_device(path: Path) -> list[str]:
    """``file:line: call`` of every tensor factory call without ``device=`` in ``path``, and of
    every ``torch.from_numpy(...)`` whose result is not moved with ``.to(...)``."""
    src = path.read_text()
    tree = ast.parse(src)
    parent = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
    bad = []
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                and isinstance(node.func.value, ast.Name) and node.func.value.id == "torch"):
            continue
        name = node.func.attr
        if name in FACTORIES:
            ok = any(k.arg == "device" for k in node.keywords)
        elif name == "from_numpy":
            up = parent.get(node)
            ok = isinstance(up, ast.Attribute) and up.attr == "to" and isinstance(parent.get(up), ast.Call)
        else:
            continue
        if not ok:
            bad.append(node)
    where = path.relative_to(REPO) if path.is_relative_to(REPO) else path.name
    return [f"{where}:{n.lineno}: {ast.get_source_segment(src, n)}" for n in sorted(bad, key=lambda n: n.lineno)]


def test_every_tensor_factory_on_the_device_paths_names_its_device() -> None:
    bad = [line for path in DEVICE_MODULES for line in _factory_calls_without_device(path)]
    assert not bad, ("tensors created on the default device (pass device=x.device, or device='cpu' where the "
                     "CPU is meant):\n" + "\n".join(bad))


def test_the_static_check_sees_what_it_should(tmp_path) -> None:
    f = tmp_path / "probe.py"
    f.write_text("import torch\n"
                 "a = torch.zeros(3)\n"
                 "b = torch.zeros(3, device=x.device)\n"
                 "c = torch.from_numpy(arr).float()\n"
                 "d = torch.from_numpy(arr).to(dev)\n"
                 "e = x.new_zeros(3)\n"
                 "f = torch.rand(2, generator=g)\n")
    found = _factory_calls_without_device(f)
    assert [line.split(":")[1] for line in found] == ["2", "4", "7"], found
