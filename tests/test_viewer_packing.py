"""The vertex columns (atgs/viewer/packing.py, layout in docs/viewer.md): decoded here with numpy,
independently of the shader, against the Gaussians they came from; non-finite Gaussians are
dropped (and only those); CPU and CUDA pack the same bytes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from atgs.gaussians import Gaussians
from atgs.viewer.packing import RECORD_BYTES, pack_gaussians
from atgs.viewer.source import SyntheticSource, decode_frame

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (torch sees none)")


def _gaussians(n: int) -> Gaussians:
    gen = torch.Generator().manual_seed(0)
    return Gaussians(torch.randn(n, 3, generator=gen), torch.randn(n, 4, generator=gen) * 3,
                     torch.rand(n, 3, generator=gen) * 0.1 + 0.01, torch.rand(n, generator=gen) * 1.2 - 0.1,
                     torch.rand(n, 3, generator=gen) * 1.2 - 0.1)


def _unpack(columns: tuple[np.ndarray, ...]) -> dict[str, np.ndarray]:
    """The documented layout, read back with numpy: float32 mean, int16 rotation (32767 q),
    float32 scale, uint16 opacity and rgb (65535 v)."""
    mean, quat, scale, orgb = columns[:4]
    assert (mean.dtype, quat.dtype, scale.dtype, orgb.dtype) == (np.float32, np.int16, np.float32, np.uint16)
    assert sum(c.nbytes for c in columns[:4]) == RECORD_BYTES * mean.shape[0]
    return {"means": mean, "quats": quat / 32767.0, "scales": scale, "opacities": orgb[:, 0] / 65535.0,
            "colors": orgb[:, 1:] / 65535.0}


def test_columns_hold_the_gaussians() -> None:
    g = _gaussians(300)
    packed = pack_gaussians(g)
    got = _unpack(packed.columns)
    np.testing.assert_array_equal(got["means"], g.means.numpy())
    np.testing.assert_array_equal(got["scales"], g.scales.numpy())
    q = g.quats.double().numpy()
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    np.testing.assert_allclose(got["quats"], q, atol=0.5 / 32767 + 1e-9)  # rounded, not truncated
    np.testing.assert_allclose(got["opacities"], np.clip(g.opacities.numpy(), 0, 1), atol=0.5 / 65535 + 1e-9)
    np.testing.assert_allclose(got["colors"], np.clip(g.colors.numpy(), 0, 1), atol=0.5 / 65535 + 1e-9)
    # the cull inputs: clamped opacity and sqrt(trace Sigma) = |scale|
    np.testing.assert_allclose(packed.opacity.numpy(), np.clip(g.opacities.numpy(), 0, 1))
    np.testing.assert_allclose(packed.extent.numpy(), np.linalg.norm(g.scales.numpy(), axis=1), rtol=1e-6)
    assert packed.sh is None and packed.sh_degree == -1


def test_sh_column_holds_the_coefficients() -> None:
    g = _gaussians(20)
    coeffs = torch.randn(20, 9, 3)
    packed = pack_gaussians(g, sh=coeffs)
    assert packed.sh_degree == 2 and packed.sh.dtype == np.float16 and packed.sh.shape == (20, 28)
    np.testing.assert_array_equal(packed.sh[:, :27], coeffs.reshape(20, 27).half().numpy())
    assert not packed.sh[:, 27:].any()  # padding
    assert not _unpack(packed.columns)["colors"].any()  # the SH replace the RGB colours


def test_non_finite_gaussians_are_dropped() -> None:
    g = _gaussians(50)
    bad = {3: ("means", float("nan")), 17: ("scales", float("inf")), 31: ("colors", float("-inf")),
           40: ("opacities", float("nan")), 44: ("quats", float("nan"))}
    for i, (field, value) in bad.items():
        t = getattr(g, field)
        if t.dim() == 1:
            t[i] = value
        else:
            t[i, 0] = value
    packed = pack_gaussians(g)
    keep = [i for i in range(50) if i not in bad]
    finite = Gaussians(*(t[keep] for t in g.as_tuple()))
    expect = pack_gaussians(finite)
    assert len(packed) == 45
    for a, b in zip(packed.columns, expect.columns):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(packed.means.numpy(), g.means[keep].numpy())
    # finite values whose sum overflows are kept (the fast check only triggers the exact one)
    huge = _gaussians(4)
    huge.means[:, 0] = 3e38
    assert len(pack_gaussians(huge)) == 4
    sh = torch.randn(50, 4, 3)
    sh[7, 2, 1] = float("nan")
    assert len(pack_gaussians(_gaussians(50), sh=sh)) == 49


def test_synthetic_source_frames_are_fresh_float32_copies() -> None:
    src = SyntheticSource(num_gaussians=200, frames=5)
    a = src.gaussians_at_frame(2)
    assert all(t.dtype == torch.float32 for t in a.as_tuple())
    a.colors[:] = 0.0  # a caller modifying its frame must not change later frames
    b = src.gaussians_at_frame(2)
    assert float(b.colors.max()) > 0.1
    np.testing.assert_allclose(b.quats.numpy(), src._quats.astype(np.float32))
    np.testing.assert_allclose(b.means.numpy(), src.gaussians_at_frame(2).means.numpy())


@needs_cuda
def test_cuda_packs_the_same_bytes_as_the_cpu() -> None:
    src = SyntheticSource(num_gaussians=3000, frames=3)
    cpu = decode_frame(src, 1, device="cpu")
    for source, device in ((src, "cuda"), (src.to("cuda"), None)):  # moved output, or decoded there
        gpu = decode_frame(source, 1, device=device)
        assert gpu.device.type == "cuda" and len(gpu) == len(cpu)
        for a, b in zip(gpu.columns, cpu.columns):
            assert a.dtype == b.dtype and a.shape == b.shape
            np.testing.assert_allclose(a.astype(np.float64), b.astype(np.float64), atol=1.0, rtol=1e-6)
        torch.testing.assert_close(gpu.extent.cpu(), cpu.extent)


def test_one_transfer_path_keeps_every_column() -> None:
    # What CUDA uses (one device buffer, one copy to the host), run here on CPU tensors.
    from atgs.viewer.packing import via_one_buffer

    packed = pack_gaussians(_gaussians(37), sh=torch.randn(37, 16, 3))
    cols = [torch.from_numpy(c) for c in packed.columns]
    for a, b in zip(via_one_buffer(cols), packed.columns):
        assert a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_array_equal(a, b)
