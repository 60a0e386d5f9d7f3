"""Exact conversions between :class:`atgs.cameras.Camera` and dataset camera formats.

- COLMAP (``pycolmap.Reconstruction``): PINHOLE / SIMPLE_PINHOLE / SIMPLE_RADIAL / RADIAL / OPENCV.
  COLMAP also puts pixel centers at +0.5, so intrinsics carry over unchanged.
- N3DV / LLFF ``poses_bounds.npy``: rows of 17 numbers, a 3x5 matrix [R | t | hwf] that maps
  camera to world with camera axes (down, right, back), then near and far. Principal point
  at the image center; rows follow the sorted video file names.
- EasyVolcap / EasyMocap ``intri.yml`` / ``extri.yml``: OpenCV FileStorage YAML with ``names``,
  ``K_<cam>``, ``dist_<cam>`` (and optional ``H_<cam>``, ``W_<cam>``) and ``Rot_<cam>``
  (or Rodrigues ``R_<cam>``), ``T_<cam>`` (world to camera). A small reader/writer lives here
  so that OpenCV is not a dependency just for two text files.
- Dynamic 3D Gaussians (Luiten et al. 2024; CMU Panoptic as they package it) ``train_meta.json`` /
  ``test_meta.json``: ``w``, ``h`` and per timestep t, per listed camera c: ``k[t][c]`` (3x3
  OpenCV intrinsics), ``w2c[t][c]`` (4x4 OpenCV world to camera), ``fn[t][c]`` (image path
  relative to ``ims/``), ``cam_id[t][c]`` (integer id). Cameras are named by their id.
- OpenGL: ``Camera.gl_view()`` / ``gl_projection()`` and :func:`camera_from_gl` back.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from atgs.cameras import CV_TO_GL, Camera
from atgs.data.errors import DataError
from atgs.rotations import matrix_to_rotvec, rotvec_to_matrix

# LLFF camera axes (down, right, back) expressed in OpenCV camera axes (right, down, forward):
# column j of c2w_llff = c2w_cv[:, :3] @ LLFF_IN_CV[:, j].
LLFF_IN_CV = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


# --- N3DV / LLFF --------------------------------------------------------------------------

def cameras_from_poses_bounds(arr: np.ndarray, names: Sequence[str],
                              sizes: Sequence[tuple[int, int]] | None = None,
                              source: str = "poses_bounds.npy") -> tuple[list[Camera], np.ndarray]:
    """Cameras and (N,2) near/far bounds from an (N,17) ``poses_bounds`` array.

    ``sizes`` optionally gives the actual (width, height) of each camera's frames; the intrinsics
    from ``hwf`` are then rescaled to that size (N3DV stores full-resolution hwf).
    """
    arr = np.asarray(arr, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 17:
        raise DataError(f"{source}: expected an (N, 17) array, got shape {arr.shape}")
    if len(arr) != len(names):
        raise DataError(f"{source}: {len(arr)} poses for {len(names)} videos ({', '.join(names)}); "
                        "rows must match the sorted video files one to one")
    cams = []
    for i, (row, name) in enumerate(zip(arr, names)):
        m = row[:15].reshape(3, 5)
        h, w, f = m[:, 4]
        c2w = np.eye(4)
        c2w[:3, :3] = m[:, :3] @ LLFF_IN_CV.T  # LLFF_IN_CV is a permutation/sign matrix: inverse = transpose
        c2w[:3, 3] = m[:, 3]
        R = c2w[:3, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0:
            raise DataError(f"{source}: row {i} ({name}) is not a rotation; is this a poses_bounds.npy file?")
        W, H = int(round(w)), int(round(h))
        K = np.array([[f, 0, w / 2.0], [0, f, h / 2.0], [0, 0, 1]])
        cam = Camera(name, W, H, K, np.linalg.inv(c2w))
        if sizes is not None and tuple(sizes[i]) != (W, H):
            cam = _resize(cam, *sizes[i])
        cams.append(cam)
    return cams, arr[:, 15:17].copy()


def _resize(cam: Camera, width: int, height: int) -> Camera:
    from dataclasses import replace

    K = cam.K.copy()
    K[0] *= width / cam.width
    K[1] *= height / cam.height
    return replace(cam, width=int(width), height=int(height), K=K)


def cameras_to_poses_bounds(cameras: Sequence[Camera], near_far: np.ndarray) -> np.ndarray:
    """(N,17) ``poses_bounds`` array. Requires fx == fy and a centered principal point (LLFF
    stores one focal length and no principal point)."""
    near_far = np.broadcast_to(np.asarray(near_far, dtype=np.float64), (len(cameras), 2))
    rows = []
    for cam in cameras:
        if abs(cam.fx - cam.fy) > 1e-9 * cam.fx or abs(cam.cx - cam.width / 2) > 1e-6 or abs(cam.cy - cam.height / 2) > 1e-6:
            raise ValueError(f"{cam.name}: poses_bounds needs fx == fy and a centered principal point")
        c2w = cam.c2w
        m = np.zeros((3, 5))
        m[:, :3] = c2w[:3, :3] @ LLFF_IN_CV
        m[:, 3] = c2w[:3, 3]
        m[:, 4] = [cam.height, cam.width, cam.fx]
        rows.append(m.reshape(-1))
    return np.concatenate([np.array(rows), near_far], axis=1)


# --- COLMAP ---------------------------------------------------------------------------------

def camera_from_colmap(colmap_camera, cam_from_world, name: str) -> Camera:
    """Camera from a ``pycolmap.Camera`` and its ``Rigid3d`` world-to-camera pose."""
    model = colmap_camera.model_name if hasattr(colmap_camera, "model_name") else str(colmap_camera.model)
    p = np.asarray(colmap_camera.params, dtype=np.float64)
    dist = None
    if model == "SIMPLE_PINHOLE":
        fx = fy = p[0]; cx, cy = p[1:3]
    elif model == "PINHOLE":
        fx, fy, cx, cy = p[:4]
    elif model == "SIMPLE_RADIAL":
        fx = fy = p[0]; cx, cy = p[1:3]; dist = np.array([p[3], 0, 0, 0, 0])
    elif model == "RADIAL":
        fx = fy = p[0]; cx, cy = p[1:3]; dist = np.array([p[3], p[4], 0, 0, 0])
    elif model == "OPENCV":
        fx, fy, cx, cy = p[:4]; dist = np.array([p[4], p[5], p[6], p[7], 0])
    else:
        raise DataError(f"camera {name}: COLMAP model {model} is not supported "
                        "(use PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL or OPENCV)")
    w2c = np.eye(4)
    w2c[:3, :4] = np.asarray(cam_from_world.matrix(), dtype=np.float64)
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    return Camera(name, int(colmap_camera.width), int(colmap_camera.height), K, w2c, dist)


def colmap_camera_of(cam: Camera, camera_id: int = 1):
    """A ``pycolmap.Camera`` with the same intrinsics (PINHOLE, or OPENCV when distorted)."""
    import pycolmap

    if cam.dist is not None:
        d = np.zeros(5)
        d[: min(5, len(cam.dist))] = cam.dist[:5]
        if abs(d[4]) > 0:
            raise ValueError(f"{cam.name}: COLMAP's OPENCV model has no k3")
        model, params = "OPENCV", [cam.fx, cam.fy, cam.cx, cam.cy, *d[:4]]
    else:
        model, params = "PINHOLE", [cam.fx, cam.fy, cam.cx, cam.cy]
    return pycolmap.Camera(model=model, width=cam.width, height=cam.height, params=params, camera_id=camera_id)


def rigid3d_of(cam: Camera):
    import pycolmap

    return pycolmap.Rigid3d(pycolmap.Rotation3d(cam.R.copy()), cam.t.reshape(3, 1).copy())


def cameras_to_reconstruction(cameras: Sequence[Camera], image_names: Sequence[str] | None = None):
    """A posed ``pycolmap.Reconstruction`` (no points): camera i gets camera/image id i + 1."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    names = image_names or [c.name for c in cameras]
    for i, (cam, name) in enumerate(zip(cameras, names)):
        rec.add_camera_with_trivial_rig(colmap_camera_of(cam, i + 1))
        img = pycolmap.Image(name=name, camera_id=i + 1, image_id=i + 1)
        rec.add_image_with_trivial_frame(img, rigid3d_of(cam))
    return rec


def cameras_from_reconstruction(rec, name_fn=None) -> list[Camera]:
    """Registered images of a reconstruction as cameras, sorted by image name.

    ``name_fn(image_name) -> camera name`` (default: the file stem, e.g. ``cam00.png`` -> ``cam00``).
    """
    name_fn = name_fn or (lambda n: Path(n).stem)
    out = []
    for img in sorted(rec.images.values(), key=lambda im: im.name):
        if not img.has_pose:
            continue
        out.append(camera_from_colmap(rec.cameras[img.camera_id], img.cam_from_world(), name_fn(img.name)))
    return out


# --- OpenGL ---------------------------------------------------------------------------------

def camera_from_gl(name: str, width: int, height: int, view: np.ndarray, proj: np.ndarray) -> Camera:
    """Inverse of ``Camera.gl_view()`` / ``Camera.gl_projection()``."""
    view, proj = np.asarray(view, np.float64), np.asarray(proj, np.float64)
    fx, fy = proj[0, 0] * width / 2.0, proj[1, 1] * height / 2.0
    cx = (1.0 - proj[0, 2]) * width / 2.0
    cy = (proj[1, 2] + 1.0) * height / 2.0
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    return Camera(name, width, height, K, CV_TO_GL @ view)  # CV_TO_GL is its own inverse


# --- EasyVolcap / EasyMocap OpenCV YAML -----------------------------------------------------

_MATRIX_RE = re.compile(
    r"^(?P<key>[A-Za-z0-9_.\-]+)\s*:\s*!!opencv-matrix\s*\n"
    r"\s+rows\s*:\s*(?P<rows>\d+)\s*\n\s+cols\s*:\s*(?P<cols>\d+)\s*\n\s+dt\s*:\s*\w+\s*\n"
    r"\s+data\s*:\s*\[(?P<data>[^\]]*)\]", re.MULTILINE)
_SCALAR_RE = re.compile(r"^(?P<key>[A-Za-z0-9_.\-]+)\s*:\s*(?P<val>[^\s!\[][^\n]*?)\s*$", re.MULTILINE)


def read_opencv_yaml(path: Path) -> dict:
    """Parse the subset of OpenCV FileStorage YAML used for camera files.

    Returns matrices as float64 arrays, scalars as float/str, and the ``names`` list as list[str].
    """
    path = Path(path)
    try:
        text = path.read_text().replace("\r\n", "\n")
    except OSError as e:
        raise DataError(f"{path}: cannot read ({e.strerror})") from None
    out: dict = {}
    for m in _MATRIX_RE.finditer(text):
        rows, cols = int(m["rows"]), int(m["cols"])
        vals = [v for v in re.split(r"[\s,]+", m["data"].strip()) if v]
        try:
            arr = np.array([float(v) for v in vals], dtype=np.float64)
        except ValueError:
            raise DataError(f"{path}: matrix {m['key']} has a non-numeric entry") from None
        if arr.size != rows * cols:
            raise DataError(f"{path}: matrix {m['key']} has {arr.size} values, expected {rows}x{cols}")
        out[m["key"]] = arr.reshape(rows, cols)
    for m in _SCALAR_RE.finditer(text):
        key, val = m["key"], m["val"].strip().strip('"').strip("'")
        if key in out or key.startswith("%") or key in ("rows", "cols", "dt", "data"):
            continue
        try:
            out[key] = float(val)
        except ValueError:
            out[key] = val
    names = re.search(r"^names\s*:\s*\n((?:\s+-\s*[^\n]*\n?)+)", text, re.MULTILINE)
    if names:
        out["names"] = [s.strip().strip('"').strip("'") for s in re.findall(r"-\s*([^\n]*)", names.group(1))]
    else:
        inline = re.search(r"^names\s*:\s*\[([^\]]*)\]", text, re.MULTILINE)
        if inline:
            out["names"] = [s.strip().strip('"').strip("'") for s in inline.group(1).split(",") if s.strip()]
    return out


def _fmt_matrix(key: str, a: np.ndarray) -> str:
    a = np.atleast_2d(np.asarray(a, dtype=np.float64))
    data = ", ".join(repr(float(v)) for v in a.reshape(-1))
    return f"{key}: !!opencv-matrix\n  rows: {a.shape[0]}\n  cols: {a.shape[1]}\n  dt: d\n  data: [{data}]\n"


def write_easyvolcap(root: Path, cameras: Sequence[Camera]) -> None:
    """Write ``intri.yml`` and ``extri.yml`` (full float precision, so round trips are exact)."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    names = "names:\n" + "".join(f'  - "{c.name}"\n' for c in cameras)
    intri, extri = ["%YAML:1.0\n---\n", names], ["%YAML:1.0\n---\n", names]
    for c in cameras:
        d = np.zeros(5)
        if c.dist is not None:
            d[: min(5, len(c.dist))] = c.dist[:5]
        intri += [_fmt_matrix(f"K_{c.name}", c.K), f"H_{c.name}: {c.height}\n", f"W_{c.name}: {c.width}\n",
                  _fmt_matrix(f"dist_{c.name}", d.reshape(1, 5))]
        extri += [_fmt_matrix(f"R_{c.name}", matrix_to_rotvec(c.R).reshape(3, 1)),
                  _fmt_matrix(f"Rot_{c.name}", c.R), _fmt_matrix(f"T_{c.name}", c.t.reshape(3, 1))]
    (root / "intri.yml").write_text("".join(intri))
    (root / "extri.yml").write_text("".join(extri))


def read_easyvolcap(root: Path, sizes: dict[str, tuple[int, int]] | None = None) -> list[Camera]:
    """Cameras from ``root/intri.yml`` and ``root/extri.yml``.

    ``sizes[name] = (width, height)`` is used when the files carry no ``H_``/``W_`` entries.
    """
    root = Path(root)
    ip, ep = root / "intri.yml", root / "extri.yml"
    for p in (ip, ep):
        if not p.is_file():
            raise DataError(f"{p}: not found (EasyVolcap scenes need intri.yml and extri.yml)")
    intri, extri = read_opencv_yaml(ip), read_opencv_yaml(ep)
    names = intri.get("names") or extri.get("names")
    if not names:
        names = sorted(k[2:] for k in intri if k.startswith("K_"))
    if not names:
        raise DataError(f"{ip}: no cameras found (no 'names' list and no K_<cam> matrices)")
    cams = []
    for n in names:
        if f"K_{n}" not in intri:
            raise DataError(f"{ip}: K_{n} missing for camera {n}")
        K = intri[f"K_{n}"].reshape(3, 3)
        dist = intri.get(f"dist_{n}", intri.get(f"D_{n}"))
        if f"Rot_{n}" in extri:
            R = extri[f"Rot_{n}"].reshape(3, 3)
        elif f"R_{n}" in extri:
            R = rotvec_to_matrix(extri[f"R_{n}"].reshape(3))
        else:
            raise DataError(f"{ep}: neither Rot_{n} nor R_{n} found for camera {n}")
        if f"T_{n}" not in extri:
            raise DataError(f"{ep}: T_{n} missing for camera {n}")
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R, extri[f"T_{n}"].reshape(3)
        if f"H_{n}" in intri and f"W_{n}" in intri:
            W, H = int(intri[f"W_{n}"]), int(intri[f"H_{n}"])
        elif sizes and n in sizes:
            W, H = sizes[n]
        else:
            raise DataError(f"{ip}: image size of camera {n} unknown (no H_{n}/W_{n} and no images)")
        cams.append(Camera(str(n), W, H, K, w2c, None if dist is None else dist.reshape(-1)))
    return cams


# --- Dynamic 3D Gaussians train_meta.json / test_meta.json ------------------------------------

D3DGS_KEYS = ("w", "h", "k", "w2c", "fn", "cam_id")


@dataclass
class D3dgsMeta:
    """One ``*_meta.json``, its cameras in ascending id order (the file lists them per timestep,
    in any order)."""

    path: Path
    width: int
    height: int
    cam_ids: list[int]
    K: np.ndarray  # (cameras, timesteps, 3, 3)
    w2c: np.ndarray  # (cameras, timesteps, 4, 4)
    files: list[list[str]]  # [camera][timestep]: image path relative to ims/


def read_d3dgs_meta(path: Path) -> D3dgsMeta:
    """Parse and check one meta file; every timestep must list every camera once."""
    path = Path(path)
    try:
        md = json.loads(path.read_text())
    except OSError as e:
        raise DataError(f"{path}: cannot read ({e.strerror})") from None
    except ValueError as e:
        raise DataError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(md, dict):
        raise DataError(f"{path}: expected a JSON object with keys {', '.join(D3DGS_KEYS)}")
    missing = [k for k in D3DGS_KEYS if k not in md]
    if missing:
        raise DataError(f"{path}: missing key {missing[0]!r} (Dynamic 3D Gaussians metas hold {', '.join(D3DGS_KEYS)})")
    w, h = md["w"], md["h"]
    if not all(type(v) is int and v > 0 for v in (w, h)):
        raise DataError(f"{path}: 'w' and 'h' must be positive integers (the image size), got {w!r} and {h!r}")
    steps = md["fn"]
    if not isinstance(steps, list) or not steps:
        raise DataError(f"{path}: 'fn' must be a non-empty list with one list of file names per timestep")
    for key in ("k", "w2c", "cam_id"):
        if not isinstance(md[key], list) or len(md[key]) != len(steps):
            raise DataError(f"{path}: {key!r} must be a list of {len(steps)} timesteps, like 'fn'")
    tracks: dict[int, list[tuple[int, np.ndarray, np.ndarray, str]]] = {}
    for t in range(len(steps)):
        ids, fns, ks, ws = (md[key][t] for key in ("cam_id", "fn", "k", "w2c"))
        if not all(isinstance(x, list) for x in (ids, fns, ks, ws)) or not len(ids) == len(fns) == len(ks) == len(ws):
            raise DataError(f"{path}: timestep {t}: 'cam_id', 'fn', 'k' and 'w2c' must be lists of one entry per camera")
        for c, (cid, fn) in enumerate(zip(ids, fns)):
            if type(cid) is not int or not isinstance(fn, str):
                raise DataError(f"{path}: cam_id[{t}][{c}] must be an integer and fn[{t}][{c}] a file name")
            K = _json_matrix(ks[c], 3, path, f"k[{t}][{c}]")
            tracks.setdefault(cid, []).append((t, K, _json_matrix(ws[c], 4, path, f"w2c[{t}][{c}]"), fn))
    for cid, track in tracks.items():
        if [t for t, *_ in track] != list(range(len(steps))):
            raise DataError(f"{path}: camera {cid} is listed {len(track)} times over {len(steps)} timesteps; "
                            "every timestep must list every camera once")
    ids = sorted(tracks)

    def stacked(j: int, n: int) -> np.ndarray:  # entry j of every (t, K, w2c, fn) as (cameras, timesteps, n, n)
        return np.array([[e[j] for e in tracks[i]] for i in ids]).reshape(len(ids), len(steps), n, n)

    return D3dgsMeta(path, w, h, ids, stacked(1, 3), stacked(2, 4), [[e[3] for e in tracks[i]] for i in ids])


def _json_matrix(value, n: int, path: Path, where: str) -> np.ndarray:
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        m = None
    if m is None or m.shape != (n, n) or not np.all(np.isfinite(m)):
        raise DataError(f"{path}: {where} is not a {n}x{n} matrix of finite numbers")
    return m


def cameras_from_d3dgs(meta: D3dgsMeta) -> list[Camera]:
    """One camera per id (named by the id). Static rigs only: a camera's ``k`` and ``w2c`` must
    be the same at every timestep, since a prepared scene holds one pose per camera. Rotations
    may be mirrored (determinant -1): the source reads the rig's world with
    :func:`atgs.data.pose_check.proper_world`."""
    cams = []
    for cid, Ks, w2cs in zip(meta.cam_ids, meta.K, meta.w2c):
        for key, m in (("k", Ks), ("w2c", w2cs)):
            moved = np.flatnonzero(~np.all(np.isclose(m, m[0], rtol=1e-6, atol=1e-6), axis=(1, 2)))
            if moved.size:
                raise DataError(f"{meta.path}: camera {cid} moves (its {key} at timestep {moved[0]} differs from "
                                "timestep 0); atgs-prepare reads static camera rigs only")
        K, w2c = Ks[0], w2cs[0]
        R = w2c[:3, :3]
        # a rotation or a mirror image of one: a mirrored world is read as such (pose_check.proper_world)
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-3) or not np.allclose(w2c[3], [0, 0, 0, 1]):
            raise DataError(f"{meta.path}: w2c of camera {cid} is not a rigid transform (its 3x3 part is not a rotation "
                            "or its last row is not 0 0 0 1); expected OpenCV world-to-camera matrices")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]):
            raise DataError(f"{meta.path}: k of camera {cid} is not a pinhole matrix [[fx,0,cx],[0,fy,cy],[0,0,1]]")
        cams.append(Camera(str(cid), meta.width, meta.height, K, w2c))
    return cams


def write_d3dgs(root: Path, cameras: Sequence[Camera], test_names: Sequence[str], num_frames: int,
                ext: str = ".jpg") -> None:
    """Write ``train_meta.json`` (the cameras not in ``test_names``) and ``test_meta.json`` over
    ``num_frames`` timesteps, naming the images ``<id>/<frame:06d><ext>`` under ``ims/`` (not
    written here). Names must be decimal ids (the format names cameras by integer) and all
    cameras one size (the metas hold one ``w``, ``h``)."""
    bad = [c.name for c in cameras if not c.name.isdigit() or str(int(c.name)) != c.name]
    if bad:
        raise ValueError(f"camera names {bad} are not decimal ids; Dynamic 3D Gaussians cameras are integers")
    sizes = {(c.width, c.height) for c in cameras}
    if len(sizes) != 1:
        raise ValueError(f"cameras of several sizes {sorted(sizes)}; the metas hold one w and h")
    (w, h), = sizes
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    test = set(test_names)
    for fname, group in (("train_meta.json", [c for c in cameras if c.name not in test]),
                         ("test_meta.json", [c for c in cameras if c.name in test])):
        md = {"w": w, "h": h,
              "k": [[c.K.tolist() for c in group] for _ in range(num_frames)],
              "w2c": [[c.w2c.tolist() for c in group] for _ in range(num_frames)],
              "fn": [[f"{c.name}/{f:06d}{ext}" for c in group] for f in range(num_frames)],
              "cam_id": [[int(c.name) for c in group] for _ in range(num_frames)]}
        (root / fname).write_text(json.dumps(md))
