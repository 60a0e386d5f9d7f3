"""Bad rasterize() input raises one clear error that names the argument."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from atgs.render import RasterInputError, rasterize


def good() -> dict:
    n = 3
    return dict(
        means=torch.tensor([[0.0, 0.0, 2.0]] * n), quats=torch.tensor([[1.0, 0, 0, 0]] * n),
        scales=torch.full((n, 3), 0.1), opacities=torch.full((n,), 0.5), colors=torch.rand(n, 3),
        viewmat=torch.eye(4), K=torch.tensor([[10.0, 0, 8], [0, 10, 8], [0, 0, 1]]), width=16, height=16,
    )  # fmt: skip


CASES = [
    ("means", torch.zeros(3, 2), "means"),
    ("quats", torch.zeros(3, 3), "quats"),
    ("scales", torch.zeros(2, 3), "scales"),
    ("opacities", torch.full((3, 1), 0.5), "opacities"),
    ("colors", torch.zeros(3, 4), "colors"),
    ("viewmat", torch.eye(3), "viewmat"),
    ("K", torch.eye(4), "K"),
    ("width", 0, "width"),
    ("height", 2.5, "height"),
    ("means", torch.zeros(3, 3, dtype=torch.int64), "means"),
    ("colors", torch.zeros(3, 3, dtype=torch.float64), "colors"),
    ("opacities", torch.tensor([0.5, float("nan"), 0.5]), "opacities"),
    ("means", torch.tensor([[0.0, 0.0, float("inf")]] * 3), "means"),
    ("viewmat", torch.full((4, 4), float("nan")), "viewmat"),
    ("opacities", torch.tensor([0.5, 1.5, 0.5]), "opacities"),
    ("scales", torch.full((3, 3), -0.1), "scales"),
    ("K", torch.tensor([[0.0, 0, 8], [0, 10, 8], [0, 0, 1]]), "K"),
    ("background", torch.zeros(4), "background"),
    ("backend", "vulkan", "backend"),
    ("colors", torch.zeros(3, 3, device="meta"), "colors"),
    ("quats", [[1, 0, 0, 0]] * 3, "quats"),
]


@pytest.mark.parametrize(("field", "value", "named"), CASES, ids=[f"{c[0]}-{i}" for i, c in enumerate(CASES)])
def test_bad_input_names_the_argument(field: str, value: object, named: str) -> None:
    args = good()
    args[field] = value
    backend = args.pop("backend", "torch")
    with pytest.raises(RasterInputError, match=f"argument '{named}'"):
        rasterize(**args, backend=backend)


def test_numpy_camera_is_accepted() -> None:
    args = good()
    args["viewmat"], args["K"] = np.eye(4), args["K"].numpy().astype(np.float64)
    out = rasterize(**args, background=np.array([0.1, 0.2, 0.3]), backend="torch")
    assert out.image.dtype == torch.float32


def test_cpu_backend_refuses_camera_gradients() -> None:
    args = good()
    args["viewmat"] = torch.eye(4, requires_grad=True)
    with pytest.raises(ValueError, match="camera"):
        rasterize(**args, backend="cpu")


def test_torch_backend_differentiates_the_camera() -> None:
    args = good()
    args["viewmat"] = torch.eye(4, requires_grad=True)
    rasterize(**args, backend="torch").image.sum().backward()
    assert args["viewmat"].grad is not None and args["viewmat"].grad.abs().sum() > 0


def test_rasterize_gaussians_with_a_camera() -> None:
    from atgs.cameras import Camera, look_at
    from atgs.gaussians import Gaussians
    from atgs.render import rasterize_gaussians

    args = good()
    cam = Camera("c", 16, 12, K=[[10.0, 0, 8], [0, 10, 6], [0, 0, 1]], w2c=look_at([0, 0, -2.0], [0, 0, 0], [0, -1, 0]))
    g = Gaussians(args["means"] - torch.tensor([0, 0, 2.0]), args["quats"], args["scales"], args["opacities"], args["colors"])
    out = rasterize_gaussians(g, cam, backend="torch")
    assert out.image.shape == (12, 16, 3) and float(out.alpha.max()) > 0.3


def test_value_checks_read_back_at_once_on_a_gpu_agree_with_the_cpu_checks() -> None:
    """device_value_flags (what a CUDA rasterize runs: one device-to-host read) finds exactly
    what the numpy checks of CPU tensors find, run here on CPU tensors."""
    from atgs.render.validate import device_value_flags, host_value_flags

    def tensors(**bad: torch.Tensor) -> dict[str, torch.Tensor]:
        t = {k: v for k, v in good().items() if isinstance(v, torch.Tensor)}
        return {**t, "background": torch.zeros(3), **bad}

    nan = float("nan")
    cases = {  # the checks each input fails
        "good": (tensors(), set()),
        "nan opacity": (tensors(opacities=torch.tensor([0.5, nan, 0.5])),
                        {"finite opacities", "opacities in [0, 1]"}),
        "inf mean": (tensors(means=torch.tensor([[0.0, 0.0, float("inf")]] * 3)), {"finite means"}),
        "opacity > 1": (tensors(opacities=torch.tensor([0.5, 1.5, 0.5])), {"opacities in [0, 1]"}),
        "opacity < 0": (tensors(opacities=torch.tensor([0.5, -0.1, 0.5])), {"opacities in [0, 1]"}),
        "negative scale": (tensors(scales=torch.full((3, 3), -0.1)), {"scales >= 0"}),
        "fy = 0": (tensors(K=torch.tensor([[10.0, 0, 8], [0, 0, 8], [0, 0, 1]])), {"focal lengths > 0"}),
        "nan background": (tensors(background=torch.tensor([0.0, nan, 0.0])), {"finite background"}),
    }
    for name, (t, failing) in cases.items():
        host, device = host_value_flags(t, 3), device_value_flags(t, 3)
        assert host == device, name
        assert {k for k, ok in host.items() if not ok} == failing, (name, host)
    empty = tensors(means=torch.zeros(0, 3), quats=torch.zeros(0, 4), scales=torch.zeros(0, 3),
                    opacities=torch.zeros(0), colors=torch.zeros(0, 3))
    assert host_value_flags(empty, 0) == device_value_flags(empty, 0) and all(host_value_flags(empty, 0).values())
