"""Real, calibrated sparse multi-camera captures as ATGS inputs (EasyVolcap layout).

Public test data of other projects, converted into ``intri.yml`` / ``extri.yml`` +
``images/<cam>/<frame:06d>.jpg`` (read by ``atgs-prepare``; ``write_easyvolcap`` keeps the lens
distortion, which ``atgs-prepare`` then removes). Nothing is downloaded here: pass the git
directory of a fetched repository (a bare mirror is read with ``git show``) or a checkout /
extracted copy of it. Never copy these data into this repository; they carry their own licences.

Sources (one function each):

- ``sleap-anipose``: github.com/talmolab/sleap-anipose, ``tests/data/minimal_session``
  (GPL-3.0). A mouse in a cage, 4 greyscale cameras (back, mid, side, top), 1280x1024,
  120 frames at 30 fps, aniposelib ``calibration.toml`` (world to camera: Rodrigues
  ``rotation``, ``translation`` in mm; ``matrix`` with OpenCV pixel centres; ``distortions``
  k1, k2, p1, p2, k3). Its ``side`` entry is a copy of ``top`` (same pose and intrinsics;
  the board corners of ``side`` reproject 125 px off), so by default ``side`` is re-fitted
  (pose, focal length, k1) to the ChArUco corners of ``calibration.metadata.h5``,
  triangulated from back, mid and top (needs h5py); ``--side drop`` leaves it out,
  ``--side keep`` writes the file as it is.
- ``deepfly3d``: github.com/NeLy-EPFL/DeepFly3D, ``tests/data/reference`` (LGPL-3.0). A
  tethered fly, 7 cameras on a ring, 960x480, 15 frames (``camera_<c>_img_<i>.jpg``); the
  calibration is the one DeepFly3D computed from them, ``tests/data/reference_df3d/
  df3d_result.pkl`` (R, tvec world to camera, ``intr``, ``distort`` all zero). ``intr`` maps
  to (column, row) pixels although its principal point reads (240, 480), the image centre in
  (row, column) order: the bundle adjustment absorbed it (f = 16041 px, so it is a 0.9 degree
  tilt); it is kept as it is, since R and t were fitted with it. The pickle is read with an
  unpickler that admits numpy arrays only.

- ``panoptic``: github.com/open-mmlab/mmpose, ``tests/data/panoptic_body3d/demo`` at commit
  bb2b14dc (mmpose is Apache-2.0; the folder was removed again at 1e72e948 and is not in the
  newest tree: the git dir is read at that commit). Images of the CMU Panoptic Studio dome:
  5 of its 31 HD cameras (00_03, 00_06, 00_12, 00_13, 00_23), 1920x1080, 5 frames each, HD
  frame numbers 4500, 5514, 6859, 9348, 13007: 34-122 s apart, so not a video (3 people
  haggling; the calibration ``160422_calib_tent13_norm`` dates them to a 160422 capture,
  presumably 160422_haggling1, VoxelPose's test sequence of that day). ``camera_parameters.json``
  holds all 31 HD cameras (K, distCoef k1 k2 p1 p2 k3, R and t world to camera in cm, the
  world's y pointing down); the converter writes the 5 with images, in metres, in a z-up world
  ((x, y, z) -> (x, z, -y): the floor is z = 0 as in the synthetic scenes). The CMU Panoptic
  data have terms of their own: "freely available for non-commercial and research purpose
  only", citing Joo et al., ICCV 2015 (github.com/CMU-Perceptual-Computing-Lab/panoptic-toolbox,
  README). The 3D body joints mmpose ships (``tests/data/panoptic_body3d/160906_band*``) belong to
  other captures without images, so ``--check`` checks the calibration on the images: SIFT
  matches between every pair against the epipolar geometry the calibration gives, and the 30
  other HD cameras' centres projected into each view, where their dark bodies should be.

All three calibrations put pixel centres at integers (OpenCV); ATGS puts them at +0.5, so 0.5 is
added to the principal point. ``--check`` prints the rig geometry and, from the 2D labels the
sources ship (SLEAP ``*.analysis.h5``, needs h5py; DeepFly3D ``points2d``), the
reprojection error of points triangulated with all cameras and with each camera left out.

Usage (repositories fetched to a git dir or checked out anywhere):

    python bench/real_rigs.py sleap-anipose /work/.mirror/talmolab+sleap-anipose/repo \\
        --out /tmp/realrigs/sleap-minimal --check
    python bench/real_rigs.py deepfly3d /work/.mirror/NeLy-EPFL+DeepFly3D/repo \\
        --out /tmp/realrigs/deepfly3d --check
    python bench/real_rigs.py panoptic /work/.mirror/open-mmlab+mmpose/repo \\
        --out /tmp/realrigs/panoptic5 --check
    atgs-prepare /tmp/realrigs/sleap-minimal --out /tmp/realrigs/sleap-minimal-prep --downscale 2
    atgs-prepare /tmp/realrigs/deepfly3d --out /tmp/realrigs/deepfly3d-prep
    atgs-prepare /tmp/realrigs/panoptic5 --out /tmp/realrigs/panoptic5-prep --downscale 6
"""

from __future__ import annotations

import argparse
import io
import itertools
import json
import pickle
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np

from atgs.cameras import Camera, distort_normalized
from atgs.data.camera_formats import write_easyvolcap
from atgs.rotations import matrix_to_rotvec, rotvec_to_matrix


# --- reading a fetched repository ----------------------------------------------------------

class Tree:
    """Files of a repository: a git dir (read at ``rev`` with ``git show``) or a folder. Paths are
    relative to the repository root; a folder may also be the data folder itself (``prefix``
    stripped)."""

    def __init__(self, path: Path, prefix: str = "", rev: str = "HEAD"):
        self.path, self.prefix, self.rev = Path(path), prefix, rev
        self.git = (self.path / "HEAD").is_file() and (self.path / "objects").is_dir()
        if not self.git and not self.path.is_dir():
            raise SystemExit(f"{self.path}: neither a git dir nor a folder")

    def _git(self, *args: str) -> bytes:
        return subprocess.run(["git", f"--git-dir={self.path}", *args], check=True, capture_output=True).stdout

    def read(self, rel: str) -> bytes:
        if self.git:
            return self._git("cat-file", "blob", f"{self.rev}:{self.prefix}{rel}")
        for p in (self.path / self.prefix / rel, self.path / rel):
            if p.is_file():
                return p.read_bytes()
        raise FileNotFoundError(f"{self.path}: {self.prefix}{rel} not found")

    def listdir(self, rel: str = "") -> list[str]:
        """Names in a folder of the tree, sorted."""
        if self.git:
            out = self._git("ls-tree", "--name-only", f"{self.rev}:{self.prefix}{rel}").decode()
            return sorted(out.split())
        for p in (self.path / self.prefix / rel, self.path / rel):
            if p.is_dir():
                return sorted(q.name for q in p.iterdir())
        raise FileNotFoundError(f"{self.path}: {self.prefix}{rel} not found")

    def commit(self) -> str | None:
        if self.git:
            return self._git("rev-parse", self.rev).decode().strip()
        return None


class _NumpyOnly(pickle.Unpickler):
    """Unpickler for result files that hold dicts of numpy arrays: any other class is refused."""

    ALLOWED = {("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
               ("numpy", "ndarray"), ("numpy", "dtype"), ("numpy.core.multiarray", "scalar"),
               ("numpy._core.multiarray", "scalar")}

    def find_class(self, module, name):
        if (module, name) not in self.ALLOWED:
            raise pickle.UnpicklingError(f"{module}.{name} is not allowed in this pickle")
        return super().find_class(module, name)


def _h5py():
    try:
        import h5py
    except ImportError:
        raise SystemExit("this step reads HDF5 files: pip install h5py "
                         "(or use --side drop / leave out --check)") from None
    return h5py


def _opencv_camera(name: str, size, K, w2c, dist) -> Camera:
    """ATGS camera from an OpenCV-convention calibration (pixel centres at integers -> +0.5)."""
    K = np.array(K, np.float64)
    K[0, 2] += 0.5
    K[1, 2] += 0.5
    return Camera(name, int(size[0]), int(size[1]), K, w2c, None if dist is None else np.asarray(dist, np.float64))


def _write_layout(out: Path, cams: list[Camera], frames: dict[str, list[bytes]], source: dict) -> None:
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise SystemExit(f"{out}: exists and is not empty")
    n = {len(v) for v in frames.values()}
    assert len(n) == 1, f"unequal frame counts {n}"
    write_easyvolcap(out, cams)
    for cam in cams:
        d = out / "images" / cam.name
        d.mkdir(parents=True)
        for i, data in enumerate(frames[cam.name]):
            (d / f"{i:06d}.jpg").write_bytes(data)
    (out / "source.json").write_text(json.dumps(source, indent=2) + "\n")
    print(f"wrote {out}: {len(cams)} cameras {[c.name for c in cams]}, {n.pop()} frames, "
          f"{cams[0].width}x{cams[0].height}")


# --- geometry checks -------------------------------------------------------------------------

def undistort_pixels(uv: np.ndarray, cam: Camera, iters: int = 30) -> np.ndarray:
    """Distorted -> pinhole pixel coordinates by damped Newton steps; NaN where the model does
    not reach (outside the radius where a negative k1 folds back)."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    if cam.dist is None:
        return uv.copy()
    xd, yd = (uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy
    x, y, h = xd.copy(), yd.copy(), 1e-7
    for _ in range(iters):
        ex, ey = distort_normalized(x, y, cam.dist)
        ax, ay = distort_normalized(x + h, y, cam.dist)
        bx, by = distort_normalized(x, y + h, cam.dist)
        J = np.stack([np.stack([ax - ex, bx - ex], -1), np.stack([ay - ey, by - ey], -1)], -2) / h
        with np.errstate(all="ignore"):
            d = np.linalg.solve(J, np.stack([ex - xd, ey - yd], -1)[..., None])[..., 0]
        n = np.linalg.norm(d, axis=-1, keepdims=True)
        d = np.where(np.isfinite(d), d * np.minimum(1.0, 0.2 / np.maximum(n, 1e-12)), 0.0)
        x, y = x - d[:, 0], y - d[:, 1]
    ex, ey = distort_normalized(x, y, cam.dist)
    out = np.stack([cam.fx * x + cam.cx, cam.fy * y + cam.cy], -1)
    out[~(np.hypot(ex - xd, ey - yd) < 1e-6)] = np.nan
    return out


def triangulate(uvs: list[np.ndarray], cams: list[Camera]) -> np.ndarray:
    """DLT of one point from its (distorted) pixel positions; NaN if fewer than 2 usable views."""
    rows = []
    for uv, c in zip(uvs, cams):
        u = undistort_pixels(uv, c)[0]
        if np.isfinite(u).all():
            P = c.K @ c.w2c[:3]
            rows += [u[0] * P[2] - P[0], u[1] * P[2] - P[1]]
    if len(rows) < 4:
        return np.full(3, np.nan)
    X = np.linalg.svd(np.array(rows))[2][-1]
    return X[:3] / X[3]


def reprojection_report(cams: list[Camera], labels: dict[str, np.ndarray], what: str,
                        point_names: list[str] | None = None) -> None:
    """labels[cam] (frames, points, 2) in ATGS pixels, NaN where unlabelled. Prints the error of
    points triangulated from all cameras (per camera, and per point when ``point_names`` is
    given), then from all but one (scored in the one left out)."""
    names = [c.name for c in cams if c.name in labels]
    by = {c.name: c for c in cams}
    F, J = next(iter(labels.values())).shape[:2]

    def run(use: list[str], target: str | None = None):
        errs, held, per_point = {n: [] for n in use}, [], {j: [] for j in range(J)}
        for f, j in itertools.product(range(F), range(J)):
            seen = [n for n in use if np.isfinite(labels[n][f, j]).all()]
            if len(seen) < 2:
                continue
            X = triangulate([labels[n][f, j] for n in seen], [by[n] for n in seen])
            if not np.isfinite(X).all():
                continue
            for n in seen:
                errs[n].append(np.linalg.norm(by[n].project(X[None])[0][0] - labels[n][f, j]))
                per_point[j].append(errs[n][-1])
            if target and np.isfinite(labels[target][f, j]).all():
                held.append(np.linalg.norm(by[target].project(X[None])[0][0] - labels[target][f, j]))
        return errs, np.array(held), per_point

    def stats(e) -> str:
        e = np.asarray(e)
        if not e.size:
            return "n=0"
        return f"n={e.size} median {np.median(e):.2f} mean {e.mean():.2f} p90 {np.percentile(e, 90):.2f} px"

    quiet = np.errstate(invalid="ignore", over="ignore", divide="ignore")  # NaN labels, far points
    with quiet:
        errs, _, per_point = run(names)
    print(f"{what}: triangulated from all of {names}: {stats(np.concatenate([np.array(v) for v in errs.values()]))}")
    for n in names:
        print(f"  {n}: {stats(errs[n])}")
    if point_names:
        print("  median per point: " + ", ".join(f"{point_names[j]} {np.median(v):.1f}"
                                                for j, v in per_point.items() if v))
    if len(names) > 2:
        for n in names:
            with quiet:
                _, held, _ = run([m for m in names if m != n], n)
            print(f"  {n} left out (triangulated from the others, projected into {n}): {stats(held)}")


def rig_report(cams: list[Camera], unit: str) -> None:
    """Centres, baselines, angles between viewing directions and where the central rays meet."""
    C = np.array([c.center for c in cams])
    # ray through the image centre (the principal point may be far off it)
    D = []
    for c in cams:
        d = c.R.T @ np.linalg.solve(c.K, [c.width / 2, c.height / 2, 1.0])
        D.append(d / np.linalg.norm(d))
    D = np.array(D)
    A, b = np.zeros((3, 3)), np.zeros(3)
    for c0, d in zip(C, D):
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c0
    m = np.linalg.solve(A, b)
    print(f"rig ({unit}): {len(cams)} cameras")
    for c, c0, d in zip(cams, C, D):
        dist_ray = np.linalg.norm((np.eye(3) - np.outer(d, d)) @ (m - c0))
        depth = (m - c0) @ d
        fov = np.degrees([c.fov_x(), c.fov_y()])
        print(f"  {c.name:>6}: centre {np.round(c0, 2)}, {np.linalg.norm(m - c0):.1f} from the meeting point, "
              f"central ray passes {dist_ray:.2f} from it (depth {depth:.1f}); f {c.fx:.1f} px, "
              f"fov {fov[0]:.1f}x{fov[1]:.1f} deg; dist {None if c.dist is None else np.round(c.dist, 4).tolist()}")
    print(f"  central rays meet nearest {np.round(m, 2)}")
    base = [np.linalg.norm(C[i] - C[j]) for i, j in itertools.combinations(range(len(cams)), 2)]
    ang = {(cams[i].name, cams[j].name): np.degrees(np.arccos(np.clip(D[i] @ D[j], -1, 1)))
           for i, j in itertools.combinations(range(len(cams)), 2)}
    print(f"  baselines min/median/max {min(base):.1f}/{np.median(base):.1f}/{max(base):.1f}")
    print("  angles between central rays (deg): " + ", ".join(f"{a}-{b} {v:.0f}" for (a, b), v in ang.items()))
    nearest = [min(v for (a, b), v in ang.items() if c.name in (a, b)) for c in cams]
    print("  each camera's nearest neighbour (deg): " + ", ".join(f"{c.name} {v:.0f}" for c, v in zip(cams, nearest)))


# --- sleap-anipose minimal_session -------------------------------------------------------------

SLEAP_PREFIX = "tests/data/minimal_session/"


def _fit_camera(name: str, size, X: np.ndarray, uv: np.ndarray, like: Camera) -> tuple[Camera, np.ndarray]:
    """Pose, focal length and k1 (principal point at the centre, as in the rest of the file) of a
    camera from 3D points and their pixel positions; starts from a DLT on points undistorted with
    ``like``'s intrinsics. Returns the camera and its per-point residuals."""
    from scipy.optimize import least_squares

    W, H = size
    uvu = undistort_pixels(uv, like)
    ok = np.isfinite(uvu[:, 0])
    A = []
    for (x, y, z), (u, v) in zip(X[ok], uvu[ok]):
        A += [[x, y, z, 1, 0, 0, 0, 0, -u * x, -u * y, -u * z, -u],
              [0, 0, 0, 0, x, y, z, 1, -v * x, -v * y, -v * z, -v]]
    M = np.linalg.solve(like.K, np.linalg.svd(np.array(A))[2][-1].reshape(3, 4))
    if np.linalg.det(M[:, :3]) < 0:
        M = -M
    U, S, Vt = np.linalg.svd(M[:, :3])

    def cam_of(p):
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = rotvec_to_matrix(p[:3]), p[3:6]
        K = np.array([[p[6], 0, W / 2], [0, p[6], H / 2], [0, 0, 1]])
        return Camera(name, W, H, K, w2c, np.array([p[7], 0, 0, 0, 0]))

    p0 = np.r_[matrix_to_rotvec(U @ Vt), M[:, 3] / S.mean(), like.fx, like.dist[0]]
    fit = least_squares(lambda p: (cam_of(p).project(X)[0] - uv).ravel(), p0, loss="huber", f_scale=2.0)
    cam = cam_of(fit.x)
    return cam, np.linalg.norm(cam.project(X)[0] - uv, axis=1)


def sleap_anipose(src: Path, out: Path, side: str = "refit", check: bool = False) -> None:
    """github.com/talmolab/sleap-anipose tests/data/minimal_session (GPL-3.0): 4 cameras, 120 frames."""
    import av

    tree = Tree(src, SLEAP_PREFIX)
    cal = tomllib.loads(tree.read("calibration.toml").decode())
    cams = []
    for key in sorted(k for k in cal if k.startswith("cam_")):
        e = cal[key]
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = rotvec_to_matrix(np.array(e["rotation"])), e["translation"]
        cams.append(_opencv_camera(e["name"], e["size"], e["matrix"], w2c, e["distortions"]))
    by = {c.name: c for c in cams}
    note = "calibration.toml as it is"
    if side != "keep":
        if side == "drop":
            cams = [c for c in cams if c.name != "side"]
            note = "camera 'side' left out: its calibration.toml entry is a copy of 'top'"
        else:
            h5py = _h5py()
            with h5py.File(io.BytesIO(tree.read("calibration.metadata.h5")), "r") as h:
                det = h["detected_corners"][()] + 0.5  # (cams, frames, corners, 2), OpenCV -> ATGS pixels
            order = [c.name for c in cams]
            good = [n for n in order if n != "side"]
            X, uv = [], []
            for f, j in itertools.product(range(det.shape[1]), range(det.shape[2])):
                seen = [n for n in good if np.isfinite(det[order.index(n), f, j]).all()]
                target = det[order.index("side"), f, j]
                if len(seen) >= 2 and np.isfinite(target).all():
                    with np.errstate(invalid="ignore", over="ignore"):
                        P = triangulate([det[order.index(n), f, j] for n in seen], [by[n] for n in seen])
                    if np.isfinite(P).all():
                        X.append(P)
                        uv.append(target)
            cam, res = _fit_camera("side", (by["side"].width, by["side"].height), np.array(X), np.array(uv), by["top"])
            cams[order.index("side")] = cam
            note = (f"camera 'side' re-fitted (pose, f, k1) to {len(X)} ChArUco corners triangulated from {good}: "
                    f"residual median {np.median(res):.2f} px, p90 {np.percentile(res, 90):.2f} px")
            print(note)
    frames = {}
    for c in cams:
        with av.open(io.BytesIO(tree.read(f"{c.name}/minimal_{c.name}.mp4"))) as container:
            frames[c.name] = []
            for fr in container.decode(video=0):
                buf = io.BytesIO()
                fr.to_image().convert("RGB").save(buf, "JPEG", quality=95)
                frames[c.name].append(buf.getvalue())
    source = {"repository": "https://github.com/talmolab/sleap-anipose", "commit": tree.commit(),
              "path": SLEAP_PREFIX, "license": "GPL-3.0", "units": "mm (ChArUco square 24 mm)", "fps": 30,
              "calibration": note}
    _write_layout(out, cams, frames, source)
    if check:
        rig_report(cams, "mm")
        h5py = _h5py()
        with h5py.File(io.BytesIO(tree.read("calibration.metadata.h5")), "r") as h:
            det = h["detected_corners"][()] + 0.5  # (cameras in calibration.toml order, frames, corners, 2)
        order = [cal[k]["name"] for k in sorted(k for k in cal if k.startswith("cam_"))]
        reprojection_report(cams, {n: det[order.index(n)] for n in by if n in [c.name for c in cams]},
                            "ChArUco corners of the calibration videos (21 frames x 70 corners)")
        labels = {}
        for c in cams:
            with h5py.File(io.BytesIO(tree.read(f"{c.name}/minimal_{c.name}_proofread.analysis.h5")), "r") as h:
                labels[c.name] = np.transpose(h["tracks"][0], (2, 1, 0)) + 0.5  # (frames, nodes, 2)
                nodes = [n.decode() for n in h["node_names"][()]]
        reprojection_report(cams, labels, "SLEAP proofread labels (15 nodes x 120 frames)", nodes)


# --- DeepFly3D tests/data/reference -----------------------------------------------------------

DF3D_PREFIX = "tests/data/"


def deepfly3d(src: Path, out: Path, check: bool = False) -> None:
    """github.com/NeLy-EPFL/DeepFly3D tests/data/reference (LGPL-3.0): 7 cameras, 15 frames."""
    from PIL import Image

    tree = Tree(src, DF3D_PREFIX)
    res = _NumpyOnly(io.BytesIO(tree.read("reference_df3d/df3d_result.pkl"))).load()
    order = [int(i) for i in res["camera_ordering"]]
    assert order == list(range(7)), f"camera_ordering {order}"
    frames, cams = {}, []
    for c in range(7):
        name = f"cam{c}"
        frames[name] = []
        for i in itertools.count():
            try:
                frames[name].append(tree.read(f"reference/camera_{c}_img_{i}.jpg"))
            except (FileNotFoundError, subprocess.CalledProcessError):
                break
        W, H = Image.open(io.BytesIO(frames[name][0])).size
        e = res[c]
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = e["R"], e["tvec"]
        cams.append(_opencv_camera(name, (W, H), e["intr"], w2c, e["distort"]))
    source = {"repository": "https://github.com/NeLy-EPFL/DeepFly3D", "commit": tree.commit(),
              "path": DF3D_PREFIX + "reference", "license": "LGPL-3.0", "units": "mm (presumably)",
              "calibration": "tests/data/reference_df3d/df3d_result.pkl as it is (+0.5 px principal point)"}
    _write_layout(out, cams, frames, source)
    if check:
        rig_report(cams, "mm?")
        p2 = np.asarray(res["points2d"], np.float64)  # (cams, frames, joints, 2) normalised (row, column)
        labels = {}
        for c, cam in enumerate(cams):
            uv = np.stack([p2[c, ..., 1] * cam.width, p2[c, ..., 0] * cam.height], -1) + 0.5
            uv[(p2[c] == 0).all(-1)] = np.nan
            # DeepFly3D uses joints 0-18 from cameras 0-2 and 19-37 from 4-6; the other half is
            # not visible there but still holds (wrong) detections
            if c in (0, 1, 2):
                uv[:, 19:] = np.nan
            elif c in (4, 5, 6):
                uv[:, :19] = np.nan
            labels[cam.name] = uv
        reprojection_report(cams, labels, "DeepFly3D 2D detections (38 joints x 15 frames)")


# --- CMU Panoptic dome, mmpose tests/data/panoptic_body3d/demo ----------------------------------

PANOPTIC_PREFIX = "tests/data/panoptic_body3d/demo/"
PANOPTIC_REV = "bb2b14dcee95971d7c6951bf0cb08edb01da1338"  # the one commit holding the demo images
# Panoptic's world has y down (the floor is y = 0, people at negative y): (x, y, z) -> (x, z, -y)
PANOPTIC_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def _panoptic_camera(e: dict) -> Camera:
    """ATGS camera (metres, z-up world) of one entry of a Panoptic calibration file."""
    w2c = np.eye(4)
    w2c[:3, :3] = np.array(e["R"], np.float64) @ PANOPTIC_Z_UP.T
    w2c[:3, 3] = np.array(e["t"], np.float64).ravel() / 100.0  # cm -> m
    return _opencv_camera(e["name"], e["resolution"], e["K"], w2c, e["distCoef"])


def panoptic(src: Path, out: Path, check: bool = False, rev: str = PANOPTIC_REV) -> None:
    """github.com/open-mmlab/mmpose tests/data/panoptic_body3d/demo (Apache-2.0; CMU Panoptic data:
    non-commercial research use): 5 HD cameras of the Panoptic dome, 5 frames each."""
    tree = Tree(src, PANOPTIC_PREFIX, rev)
    cal = json.loads(tree.read("camera_parameters.json"))
    every = {e["name"]: _panoptic_camera(e) for e in cal["cameras"] if e.get("type", "hd") == "hd"}
    names = [n for n in tree.listdir() if n in every]
    files = {n: [f for f in tree.listdir(n) if f.endswith(".jpg")] for n in names}
    numbers = {n: [f.rsplit("_", 1)[1][:-4] for f in v] for n, v in files.items()}
    if len({tuple(v) for v in numbers.values()}) != 1:
        raise SystemExit(f"{src}: the cameras hold different frames: {numbers}")
    cams = [every[n] for n in names]
    frames = {n: [tree.read(f"{n}/{f}") for f in files[n]] for n in names}
    source = {"repository": "https://github.com/open-mmlab/mmpose", "commit": tree.commit(), "path": PANOPTIC_PREFIX,
              "license": "mmpose: Apache-2.0; the images and calibration are CMU Panoptic Studio data: "
                         "non-commercial research use only, cite Joo et al. ICCV 2015",
              "units": "m (Panoptic's cm / 100)", "world": "z up: Panoptic (x, y, z) -> (x, z, -y)",
              "calibration": f"camera_parameters.json ({cal.get('calibDataSource')}) as it is "
                             "(+0.5 px principal point)",
              "frames": [int(x) for x in numbers[names[0]]],
              "note": "HD frame numbers at 29.97 fps: 34-122 s apart, not a video"}
    _write_layout(out, cams, frames, source)
    if check:
        rig_report(cams, "m")
        images = {n: _grey(frames[n][0]) for n in names}
        epipolar_report(cams, images)
        bodies_report(cams, [c for n, c in every.items() if n not in names] + cams, images)


def _grey(data: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)).convert("L"))


def sift_features(img: np.ndarray, max_features: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    """SIFT keypoints (N,2), ATGS pixel convention (COLMAP's puts pixel centres at +0.5 too), and
    unit descriptors of a grey image."""
    import warnings

    import pycolmap

    opts = pycolmap.FeatureExtractionOptions()
    opts.sift.max_num_features = max_features
    opts.max_image_size = max(img.shape)
    old, pycolmap.logging.minloglevel = pycolmap.logging.minloglevel, 2
    try:
        with warnings.catch_warnings():  # pycolmap.Sift is deprecated; its replacement returns no arrays
            warnings.simplefilter("ignore", DeprecationWarning)
            kp, desc = pycolmap.Sift(opts, pycolmap.Device.cpu).extract(np.ascontiguousarray(img))
    finally:
        pycolmap.logging.minloglevel = old
    desc = desc.astype(np.float32)
    return kp[:, :2].astype(np.float64), desc / (np.linalg.norm(desc, axis=1, keepdims=True) + 1e-12)


def sift_matches(fa, fb, ratio: float = 0.75) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours that pass Lowe's ratio test: matched pixel positions in each."""
    (ka, da), (kb, db) = fa, fb
    d = np.sqrt(np.maximum(2.0 - 2.0 * da @ db.T, 0.0))
    best, second = np.argsort(d, axis=1)[:, :2].T
    rows = np.arange(len(da))
    keep = (d[rows, best] < ratio * d[rows, second]) & (np.argmin(d, axis=0)[best] == rows)
    return ka[keep], kb[best[keep]]


def epipolar_distances(ca: Camera, cb: Camera, ua: np.ndarray, ub: np.ndarray) -> np.ndarray:
    """Symmetric distance (px, undistorted) of matched pixels to the epipolar lines of the calibration."""
    pa, pb = undistort_pixels(ua, ca), undistort_pixels(ub, cb)
    rel = cb.w2c @ np.linalg.inv(ca.w2c)
    t = rel[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    F = np.linalg.inv(cb.K).T @ tx @ rel[:3, :3] @ np.linalg.inv(ca.K)
    ha, hb = np.c_[pa, np.ones(len(pa))], np.c_[pb, np.ones(len(pb))]
    la, lb = ha @ F.T, hb @ F  # lines in b of the points of a, and in a of the points of b
    num = np.abs((hb * la).sum(1))
    return 0.5 * (num / np.hypot(la[:, 0], la[:, 1]) + num / np.hypot(lb[:, 0], lb[:, 1]))


def epipolar_report(cams: list[Camera], images: dict[str, np.ndarray]) -> None:
    """Per pair: SIFT matches and their distance to the calibration's epipolar lines. Across wide
    baselines and repeated wall panels most matches are wrong, so what tells is the share within
    2 px against the share of the same matches paired at random (the chance of landing near a
    line), and the distance of those within 2 px."""
    print("calibration against SIFT matches (first frame; epipolar distance in px; chance: the matches shuffled):")
    rng = np.random.default_rng(0)
    feats = {c.name: sift_features(images[c.name]) for c in cams}
    for ca, cb in itertools.combinations(cams, 2):
        ua, ub = sift_matches(feats[ca.name], feats[cb.name])
        with np.errstate(invalid="ignore"):
            e = epipolar_distances(ca, cb, ua, ub)
            chance = np.concatenate([epipolar_distances(ca, cb, ua, ub[rng.permutation(len(ub))]) for _ in range(20)])
        e, chance = e[np.isfinite(e)], chance[np.isfinite(chance)]
        if not e.size:
            print(f"  {ca.name}-{cb.name}: no matches")
            continue
        near = e[e < 2]
        print(f"  {ca.name}-{cb.name}: {e.size} matches, {100 * np.mean(e < 2):.0f} % within 2 px (chance "
              f"{100 * np.mean(chance < 2):.1f} %), their median {np.median(near) if near.size else np.nan:.2f} px")


def bodies_report(cams: list[Camera], others: list[Camera], images: dict[str, np.ndarray], win: int = 12) -> None:
    """The other cameras' centres projected into each view: a camera body is a dark box on the
    light wall, so the darkest pixel within ``win`` px of a right projection is dark, unlike at
    the same places shifted by 5 % of the image (people in front of a body make a few misses)."""
    print(f"other cameras' centres projected into each view (darkest grey level within {win} px; 0-255):")
    for cam in cams:
        img = images[cam.name].astype(np.float64)
        H, W = img.shape
        pts = np.array([o.center for o in others if o.name != cam.name])
        uv, z = cam.project(pts)
        inside = (z > 0) & (uv[:, 0] >= win) & (uv[:, 0] < W - win) & (uv[:, 1] >= win) & (uv[:, 1] < H - win)

        def darkest(p):
            return np.array([img[int(v) - win:int(v) + win + 1, int(u) - win:int(u) + win + 1].min() for u, v in p])

        if not inside.any():
            print(f"  {cam.name}: no other camera in view")
            continue
        at = darkest(uv[inside])
        shift = uv[inside] + np.array([0.05 * W, 0.05 * H])
        shift = shift[(shift[:, 0] < W - win) & (shift[:, 1] < H - win)]
        off = darkest(shift)
        print(f"  {cam.name}: {inside.sum()} cameras in view; darkest at them: median {np.median(at):.0f} "
              f"({np.mean(at < 60) * 100:.0f} % below 60); shifted: median {np.median(off):.0f} "
              f"({np.mean(off < 60) * 100:.0f} % below 60)")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("source", choices=["sleap-anipose", "deepfly3d", "panoptic"])
    ap.add_argument("repo", type=Path, help="git dir of the fetched repository, or a checkout/extracted folder")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--side", choices=["refit", "drop", "keep"], default="refit",
                    help="sleap-anipose: what to do with the 'side' camera (its calibration is top's)")
    ap.add_argument("--check", action="store_true", help="print rig geometry and label reprojection errors")
    a = ap.parse_args(argv)
    if a.source == "sleap-anipose":
        sleap_anipose(a.repo, a.out, a.side, a.check)
    elif a.source == "panoptic":
        panoptic(a.repo, a.out, a.check)
    else:
        deepfly3d(a.repo, a.out, a.check)


if __name__ == "__main__":
    sys.exit(main())
