"""The 3DGS PLY format (atgs.io.gaussian_ply): the bytes the writer produces against the 3DGS
layout parsed by hand, read-back of every property, files as other tools write them (ASCII, big
endian, doubles, extra properties, another order), and one-line errors for bad files."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from atgs.gaussians import Gaussians
from atgs.io.gaussian_ply import (GaussianPlyError, property_names, read_gaussian_ply, read_gaussian_ply_layout,
                                  write_gaussian_ply)

SQRT_PI = math.sqrt(math.pi)  # 0.5 / SH_C0: the f_dc of a colour 0.5 away from grey


def _parse_by_hand(path: Path) -> tuple[list[str], np.ndarray]:
    """Header lines and the (N, P) float32 body of a binary little-endian PLY of float properties."""
    raw = path.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    header = raw[:end].decode("ascii").splitlines()
    props = [ln.split()[2] for ln in header if ln.startswith("property ")]
    assert all(ln.split()[1] == "float" for ln in header if ln.startswith("property "))
    body = np.frombuffer(raw[end:], dtype="<f4").reshape(-1, len(props))
    return header, body


def _two_gaussians() -> Gaussians:
    return Gaussians(means=torch.tensor([[1.0, -2.0, 3.0], [0.25, 0.5, -0.75]]),
                     quats=torch.tensor([[0.9, 0.1, -0.2, 0.3], [1.0, 0.0, 0.0, 0.0]]),  # first one not normalized
                     scales=torch.tensor([[0.5, 2.0, 1.0], [0.01, 0.1, 1.0]]),
                     opacities=torch.tensor([0.75, 0.2]),
                     colors=torch.tensor([[1.0, 0.5, 0.0], [0.5, 0.5, 0.5]]))


def test_degree_0_file_is_the_3dgs_layout_with_logit_log_and_sh0(tmp_path: Path) -> None:
    path = write_gaussian_ply(tmp_path / "a.ply", _two_gaussians())
    header, body = _parse_by_hand(path)
    assert header[:2] == ["ply", "format binary_little_endian 1.0"] and "element vertex 2" in header
    props = [ln.split()[2] for ln in header if ln.startswith("property ")]
    assert props == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                     "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    col = {name: body[:, i] for i, name in enumerate(props)}
    np.testing.assert_array_equal(np.stack([col["x"], col["y"], col["z"]], 1), [[1, -2, 3], [0.25, 0.5, -0.75]])
    assert not np.any(body[:, 3:6])  # normals are zeros, as 3DGS writes them
    # colour (1, 0.5, 0) = 0.5 + C0 f_dc with C0 = 1 / (2 sqrt(pi)): f_dc = (sqrt(pi), 0, -sqrt(pi))
    np.testing.assert_allclose(np.stack([col[f"f_dc_{c}"] for c in range(3)], 1), [[SQRT_PI, 0, -SQRT_PI], [0, 0, 0]],
                               atol=1e-6)
    np.testing.assert_allclose(col["opacity"], [math.log(3.0), math.log(0.25)], rtol=1e-6)  # logit(0.75), logit(0.2)
    np.testing.assert_allclose(np.stack([col[f"scale_{i}"] for i in range(3)], 1),
                               [[math.log(0.5), math.log(2.0), 0.0], [math.log(0.01), math.log(0.1), 0.0]], rtol=1e-6)
    np.testing.assert_array_equal(np.stack([col[f"rot_{i}"] for i in range(4)], 1),
                                  np.float32([[0.9, 0.1, -0.2, 0.3], [1, 0, 0, 0]]))  # w x y z, as given


def test_f_rest_is_channel_major(tmp_path: Path) -> None:
    g = _two_gaussians()
    sh = torch.zeros(2, 4, 3)  # degree 1: coefficient k of channel c = 100 c + k
    for k in range(4):
        for c in range(3):
            sh[:, k, c] = 100 * c + k
    header, body = _parse_by_hand(write_gaussian_ply(tmp_path / "a.ply", g, sh))
    props = [ln.split()[2] for ln in header if ln.startswith("property ")]
    rest = body[0, [props.index(f"f_rest_{i}") for i in range(9)]]
    np.testing.assert_array_equal(rest, [1, 2, 3, 101, 102, 103, 201, 202, 203])  # all r, then g, then b
    np.testing.assert_array_equal(body[0, [props.index(f"f_dc_{c}") for c in range(3)]], [0, 100, 200])
    assert props.index("f_rest_8") + 1 == props.index("opacity")


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_read_back_every_property(tmp_path: Path, degree: int) -> None:
    gen = torch.Generator().manual_seed(degree)
    n, K = 50, (degree + 1) ** 2
    g = Gaussians(torch.randn(n, 3, generator=gen), torch.randn(n, 4, generator=gen),
                  torch.rand(n, 3, generator=gen) + 1e-3, torch.rand(n, generator=gen) * 0.98 + 0.01,
                  torch.zeros(n, 3))
    sh = torch.randn(n, K, 3, generator=gen)
    path = write_gaussian_ply(tmp_path / "a.ply", g, sh)
    layout = read_gaussian_ply_layout(path)
    assert layout.sh_degree == degree and layout.count == n and layout.properties == property_names(degree)
    assert len(layout.properties) == 17 + 3 * (K - 1)  # 62 at degree 3, as 3DGS writes
    back = read_gaussian_ply(path)
    assert back.sh_degree == degree
    torch.testing.assert_close(back.sh, sh, rtol=0, atol=0)
    for name in ("means", "quats"):
        torch.testing.assert_close(getattr(back.gaussians, name), getattr(g, name), rtol=0, atol=0)
    torch.testing.assert_close(back.gaussians.scales, g.scales, rtol=1e-6, atol=0)  # exp(log(s))
    torch.testing.assert_close(back.gaussians.opacities, g.opacities, rtol=1e-6, atol=1e-7)  # sigmoid(logit(o))
    torch.testing.assert_close(back.gaussians.colors, (0.5 + 0.28209479177387814 * sh[:, 0]).clamp(0, 1))


def test_opacity_0_and_1_and_scale_0_stay_finite(tmp_path: Path) -> None:
    g = _two_gaussians()
    g.opacities = torch.tensor([0.0, 1.0])
    g.scales[0, 0] = 0.0
    _, body = _parse_by_hand(write_gaussian_ply(tmp_path / "a.ply", g))
    assert np.isfinite(body).all()
    back = read_gaussian_ply(tmp_path / "a.ply").gaussians
    assert float(back.opacities[0]) < 1e-6 and float(back.opacities[1]) > 1 - 1e-6 and float(back.scales[0, 0]) < 1e-20


def _foreign_rows(n: int, dtype: str, order: list[str], gen: np.random.Generator) -> tuple[np.ndarray, dict]:
    """Rows as another tool might write them: properties in ``order`` of type ``dtype`` plus
    extra ones (uchar colours, a filter_3D float), with the values each property holds."""
    values = {name: gen.normal(size=n) for name in order}
    fields = [(name, dtype) for name in order] + [("red", "u1"), ("green", "u1"), ("blue", "u1"), ("filter_3D", "f4")]
    rows = np.zeros(n, dtype=fields)
    for name in order:
        rows[name] = values[name]
    rows["red"], rows["filter_3D"] = 200, 0.5
    return rows, values


@pytest.mark.parametrize("text,byte_order,dtype", [(True, "=", "f8"), (False, ">", "f8"), (False, ">", "f4"),
                                                    (False, "<", "f8")])
def test_files_of_other_tools_open(tmp_path: Path, text: bool, byte_order: str, dtype: str) -> None:
    gen = np.random.default_rng(3)
    names = list(property_names(1))
    names.remove("nx"), names.remove("ny"), names.remove("nz")  # some writers leave the normals out
    order = list(reversed(names))  # and nothing requires 3DGS's order
    rows, values = _foreign_rows(20, dtype, order, gen)
    path = tmp_path / "foreign.ply"
    faces = np.zeros(1, dtype=[("vertex_indices", "i4", (3,))])
    PlyData([PlyElement.describe(rows, "vertex"), PlyElement.describe(faces, "face")], text=text,
            byte_order=byte_order).write(str(path))
    back = read_gaussian_ply(path)
    v = {k: torch.tensor(a, dtype=torch.float32) for k, a in values.items()}
    torch.testing.assert_close(back.gaussians.means, torch.stack([v["x"], v["y"], v["z"]], 1))
    torch.testing.assert_close(back.gaussians.quats, torch.stack([v[f"rot_{i}"] for i in range(4)], 1))
    torch.testing.assert_close(back.gaussians.scales, torch.exp(torch.stack([v[f"scale_{i}"] for i in range(3)], 1)))
    torch.testing.assert_close(back.gaussians.opacities, torch.sigmoid(v["opacity"]))
    for c in range(3):
        torch.testing.assert_close(back.sh[:, 0, c], v[f"f_dc_{c}"])
        for k in range(1, 4):
            torch.testing.assert_close(back.sh[:, k, c], v[f"f_rest_{c * 3 + k - 1}"])
    assert back.sh.dtype == torch.float32 and back.gaussians.means.dtype == torch.float32


def _write_floats(path: Path, names: list[str], n: int = 3) -> Path:
    rows = np.zeros(n, dtype=[(name, "<f4") for name in names])
    PlyData([PlyElement.describe(rows, "vertex")], byte_order="<").write(str(path))
    return path


def _error(path: Path) -> str:
    with pytest.raises(GaussianPlyError) as info:
        read_gaussian_ply(path)
    msg = str(info.value)
    assert "\n" not in msg and str(path) in msg, msg
    with pytest.raises(GaussianPlyError):
        read_gaussian_ply_layout(path)
    return msg


def test_bad_files_are_one_line_errors_naming_the_file(tmp_path: Path) -> None:
    good = write_gaussian_ply(tmp_path / "good.ply", _two_gaussians())
    names = list(property_names(0))
    assert "'opacity' is missing" in _error(_write_floats(tmp_path / "no_opacity.ply",
                                                          [n for n in names if n != "opacity"]))
    assert "'rot_3' is missing" in _error(_write_floats(tmp_path / "no_rot3.ply", [n for n in names if n != "rot_3"]))
    msg = _error(_write_floats(tmp_path / "rest12.ply", names + [f"f_rest_{i}" for i in range(12)]))
    assert "12 f_rest_* properties" in msg and "0, 9, 24 or 45" in msg
    gap = names + [f"f_rest_{i}" for i in range(10) if i != 4]
    assert "'f_rest_4' is missing" in _error(_write_floats(tmp_path / "gap.ply", gap))
    truncated = tmp_path / "truncated.ply"
    truncated.write_bytes(good.read_bytes()[:-10])
    assert "truncated or corrupt" in _error(truncated)
    header_only = tmp_path / "cut_header.ply"
    header_only.write_bytes(good.read_bytes()[:60])
    _error(header_only)
    for name, data in (("empty.ply", b""), ("junk.ply", b"\x00\xffnot a ply" * 20), ("text.ply", b"hello\n")):
        (tmp_path / name).write_bytes(data)
        assert "not a readable PLY file" in _error(tmp_path / name)
    half = tmp_path / "half.ply"  # the PLY format has no 16-bit float type: a clear error, not a crash
    half.write_bytes(good.read_bytes().replace(b"property float opacity", b"property half opacity"))
    _error(half)
    points = tmp_path / "points.ply"
    PlyData([PlyElement.describe(np.zeros(2, dtype=[("x", "f4")]), "point")]).write(str(points))
    assert "without a 'vertex' element" in _error(points)
    assert "not found" in _error(tmp_path / "missing.ply")
