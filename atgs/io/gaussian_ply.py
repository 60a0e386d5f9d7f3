"""The 3D Gaussian splatting PLY format: the project's one reader and writer of it.

A 3DGS PLY (the layout of Kerbl et al. 2023, which SuperSplat, gsplat's examples and most web
viewers read) is one ``vertex`` element of float properties, one row per Gaussian, in this order::

    x y z                 mean
    nx ny nz              unused normals (written as zeros, as 3DGS does)
    f_dc_0 f_dc_1 f_dc_2  degree-0 spherical-harmonic (SH) coefficient of r, g, b
    f_rest_0 ...          the higher SH coefficients, channel-major: all of r's K-1, then g's, then b's
    opacity               logit of the opacity (sigmoid gives it back)
    scale_0 scale_1 scale_2  log of the standard deviations
    rot_0 rot_1 rot_2 rot_3  rotation quaternion w, x, y, z (need not be normalized)

With ``K = (degree + 1)^2`` coefficients per channel there are ``3 (K - 1)`` f_rest properties:
0, 9, 24 or 45 for SH degree 0..3. The colour seen along ``d`` is ``max(0.5 + SH(d), 0)``
(:mod:`atgs.sh`, whose coefficient order ``(N, K, 3)`` this module converts from and to).

:func:`write_gaussian_ply` writes binary little-endian files atomically. :func:`read_gaussian_ply`
reads what other 3DGS tools write too: ASCII or binary of either byte order (through plyfile),
properties in any order, any numeric type (converted to float32), unknown properties ignored.
A missing required property, an f_rest count that is no SH degree, a truncated or corrupt file
raise :class:`GaussianPlyError` with one line naming the file. :func:`read_gaussian_ply_layout`
checks a file's header without reading its data (binary files are memory-mapped), which is how a
folder of per-frame files is checked up front.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from atgs.errors import UserError
from atgs.gaussians import Gaussians
from atgs.io.atomic import atomic_file
from atgs.sh import MAX_SH_DEGREE, num_sh_coeffs, rgb_to_sh0, sh0_to_rgb, sh_degree_of

ELEMENT = "vertex"
MEANS = ("x", "y", "z")
NORMALS = ("nx", "ny", "nz")
DC = ("f_dc_0", "f_dc_1", "f_dc_2")
OPACITY = "opacity"
SCALES = ("scale_0", "scale_1", "scale_2")
ROTATION = ("rot_0", "rot_1", "rot_2", "rot_3")
REQUIRED = (*MEANS, *DC, OPACITY, *SCALES, *ROTATION)
REST_COUNTS = {3 * (num_sh_coeffs(d) - 1): d for d in range(MAX_SH_DEGREE + 1)}  # 0, 9, 24, 45 -> 0..3
# Opacities are clamped into (0, 1) before the logit so that 0 and 1 stay finite; both bounds
# are far below what a render can show (alpha is cut below 1/255 and capped at 0.99).
OPACITY_EPS = 1e-7
MIN_SCALE = 1e-30  # log(0) would be -inf


class GaussianPlyError(UserError):
    """A file that is not a readable 3DGS PLY; the message is one line naming the file."""


def rest_name(i: int) -> str:
    return f"f_rest_{i}"


def property_names(sh_degree: int) -> tuple[str, ...]:
    """The properties of a 3DGS PLY of ``sh_degree``, in the order 3DGS writes them."""
    rest = tuple(rest_name(i) for i in range(3 * (num_sh_coeffs(sh_degree) - 1)))
    return (*MEANS, *NORMALS, *DC, *rest, OPACITY, *SCALES, *ROTATION)


@dataclass(frozen=True)
class GaussianPlyLayout:
    """What a file's header says: how many Gaussians, which properties, which SH degree."""

    path: Path
    count: int
    properties: tuple[str, ...]  # every property of the vertex element, in file order
    sh_degree: int
    encoding: str  # "ascii", "binary_little_endian" or "binary_big_endian"


@dataclass
class GaussianPly:
    """The Gaussians of one file in the project's types: activated opacities and scales, the
    colour of the degree-0 term (clamped to [0, 1]) in ``gaussians.colors``, and every SH
    coefficient in ``sh`` (N, K, 3), atgs.sh's order."""

    gaussians: Gaussians
    sh: torch.Tensor

    @property
    def sh_degree(self) -> int:
        return sh_degree_of(self.sh.shape[1])


# --- writing ---------------------------------------------------------------------------------------

def logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(np.asarray(p, dtype=np.float64), OPACITY_EPS, 1.0 - OPACITY_EPS)
    return np.log(p) - np.log1p(-p)


def gaussian_ply_rows(gaussians: Gaussians, sh: torch.Tensor | None = None) -> np.ndarray:
    """(N,) structured float32 array of the 3DGS properties of ``gaussians``: SH coefficients
    ``sh`` (N, K, 3) in atgs.sh's order, or without them degree 0 from ``gaussians.colors``."""
    n = len(gaussians)
    if sh is None:
        sh = rgb_to_sh0(gaussians.colors.detach().float())[:, None, :]
    sh = sh.detach().cpu().float()
    if sh.ndim != 3 or sh.shape[0] != n or sh.shape[2] != 3:
        raise ValueError(f"SH coefficients of shape {tuple(sh.shape)}: expected ({n}, K, 3)")
    K = sh.shape[1]
    names = property_names(sh_degree_of(K))
    cols = np.zeros((n, len(names)), dtype="<f4")

    def put(first: str, values: np.ndarray) -> None:
        i = names.index(first)
        cols[:, i : i + values.shape[1]] = values

    cpu = gaussians.detach().to("cpu")
    put("x", cpu.means.float().numpy())
    put("f_dc_0", sh[:, 0, :].numpy())
    if K > 1:  # channel-major: r's K-1 coefficients, then g's, then b's
        put("f_rest_0", sh[:, 1:, :].transpose(1, 2).reshape(n, 3 * (K - 1)).numpy())
    put(OPACITY, logit(cpu.opacities.numpy())[:, None])
    put("scale_0", np.log(np.maximum(cpu.scales.double().numpy(), MIN_SCALE)))
    put("rot_0", cpu.quats.float().numpy())
    return cols.view(np.dtype([(name, "<f4") for name in names])).reshape(n)


def write_gaussian_ply(path: str | Path, gaussians: Gaussians, sh: torch.Tensor | None = None) -> Path:
    """Write a binary little-endian 3DGS PLY atomically (see :func:`gaussian_ply_rows`)."""
    from plyfile import PlyData, PlyElement

    rows = gaussian_ply_rows(gaussians, sh)
    ply = PlyData([PlyElement.describe(rows, ELEMENT)], text=False, byte_order="<",
                  comments=["3D Gaussian splatting PLY written by atgs"])
    with atomic_file(path, suffix=".ply") as tmp:
        ply.write(str(tmp))
    return Path(path)


# --- reading ---------------------------------------------------------------------------------------

def _open(path: Path):
    """(vertex element, encoding) of a PLY file; binary data stays memory-mapped."""
    from plyfile import PlyData, PlyParseError

    if not path.is_file():
        raise GaussianPlyError(f"{path}: PLY file not found")
    try:
        data = PlyData.read(str(path), mmap="c")
    except (PlyParseError, ValueError, UnicodeDecodeError, OSError, MemoryError) as e:
        detail = " ".join(str(e).split()) or type(e).__name__
        # plyfile lists every type it knows after an unknown one (e.g. 'half': PLY has no 16-bit float)
        detail = re.sub(r" not in \[.*\]", " is not a PLY property type", detail)
        raise GaussianPlyError(f"{path}: not a readable PLY file, truncated or corrupt ({detail}); "
                               "re-export or re-download it") from None
    names = [el.name for el in data.elements]
    if ELEMENT not in names:
        raise GaussianPlyError(f"{path}: PLY file without a '{ELEMENT}' element (it has {names}); "
                               "not a 3D Gaussian splatting file")
    encoding = "ascii" if data.text else "binary_big_endian" if data.byte_order == ">" else "binary_little_endian"
    return data[ELEMENT], encoding


def _layout(path: Path, element, encoding: str) -> GaussianPlyLayout:
    from plyfile import PlyListProperty

    props = tuple(p.name for p in element.properties)
    listed = [p.name for p in element.properties if isinstance(p, PlyListProperty)]
    present = set(props)
    for name in REQUIRED:
        if name not in present:
            raise GaussianPlyError(f"{path}: property '{name}' is missing; a 3D Gaussian splatting PLY needs "
                                   f"{' '.join(REQUIRED)} (and f_rest_* for SH degree 1-3)")
    if any(name in REQUIRED or name.startswith("f_rest_") for name in listed):
        raise GaussianPlyError(f"{path}: properties {listed} are lists; 3DGS properties are single numbers")
    rest = [n for n in props if re.fullmatch(r"f_rest_\d+", n)]
    if len(rest) not in REST_COUNTS:
        raise GaussianPlyError(f"{path}: {len(rest)} f_rest_* properties; expected 0, 9, 24 or 45 "
                               "(spherical harmonics of degree 0, 1, 2 or 3)")
    missing = [rest_name(i) for i in range(len(rest)) if rest_name(i) not in present]
    if missing:
        raise GaussianPlyError(f"{path}: property '{missing[0]}' is missing (f_rest_0..f_rest_{len(rest) - 1} "
                               "must all be present)")
    return GaussianPlyLayout(path, int(element.count), props, REST_COUNTS[len(rest)], encoding)


def read_gaussian_ply_layout(path: str | Path) -> GaussianPlyLayout:
    """Check a file's header (and, for binary files, its length) without reading its data."""
    path = Path(path)
    element, encoding = _open(path)
    return _layout(path, element, encoding)


def read_gaussian_ply(path: str | Path) -> GaussianPly:
    """Read a 3DGS PLY into the project's types (see :class:`GaussianPly`)."""
    path = Path(path)
    element, encoding = _open(path)
    layout = _layout(path, element, encoding)
    data = element.data

    def cols(names) -> torch.Tensor:
        return torch.from_numpy(np.stack([np.asarray(data[n], dtype=np.float32) for n in names], 1))

    n = layout.count
    K = num_sh_coeffs(layout.sh_degree)
    dc = cols(DC)
    if K > 1:
        rest = cols([rest_name(i) for i in range(3 * (K - 1))]).reshape(n, 3, K - 1).transpose(1, 2)
        sh = torch.cat([dc[:, None, :], rest], 1).contiguous()
    else:
        sh = dc[:, None, :].contiguous()
    g = Gaussians(means=cols(MEANS), quats=cols(ROTATION), scales=torch.exp(cols(SCALES)),
                  opacities=torch.sigmoid(cols((OPACITY,))[:, 0]), colors=sh0_to_rgb(dc).clamp(0.0, 1.0))
    return GaussianPly(g, sh)
