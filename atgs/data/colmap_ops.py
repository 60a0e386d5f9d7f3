"""pycolmap (CPU) steps of the ingest: SfM for unposed cameras, known-pose triangulation, and
the verified feature matches that check given poses (atgs.data.pose_check).

Dense stereo (``patch_match_stereo``) needs CUDA, so keyframe points come from sparse
SIFT matching + triangulation with the camera poses held fixed.

Pitfall handled here: the reconstruction handed to ``triangulate_points`` must use the image
and camera ids of the database, so the database is filled first and its ids are read back by
image name (:func:`database_ids`): COLMAP numbers the images in its own order (the names sorted
as strings, so ``10/000000.png`` comes before ``2/000000.png``), never in the caller's.
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from atgs.cameras import Camera
from atgs.data.camera_formats import camera_from_colmap, colmap_camera_of, rigid3d_of
from atgs.data.errors import DataError


@dataclass(frozen=True)
class ColmapOptions:
    max_image_size: int = 1600  # SIFT on at most this many pixels along the long side
    max_num_features: int = 8192
    min_track_length: int = 2
    max_reproj_error: float = 2.0  # px; triangulated points above this are dropped
    min_tri_angle: float = 1.5  # degrees
    two_view_tracks: bool = True  # also keep points seen by only two cameras: ~2x points, same median error
    sift_peak_threshold: float = 0.004  # COLMAP default 0.0067; lower finds more (weaker) features in small frames
    num_threads: int = -1


RANDOM_SEED = 0  # every COLMAP stage that samples (verification, triangulation, mapping): same input, same points


@contextlib.contextmanager
def _quiet_glog(where: Path | None = None):
    """COLMAP logs through glog to stderr; keep the console for our progress bars. pycolmap
    failures (check failures surface as ValueError/RuntimeError) become one-line DataErrors.
    Its ERROR lines are silenced too (level 3: only FATAL, which aborts): every failure they
    announce ("Failed to create any sparse model") reaches the user as our own one line."""
    import pycolmap

    old = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 3
    try:
        yield
    except (ValueError, RuntimeError) as e:
        if isinstance(e, DataError):
            raise
        first = str(e).strip().splitlines()[0][:200] if str(e).strip() else type(e).__name__
        raise DataError(f"{where}: pycolmap failed ({first})") from None
    finally:
        pycolmap.logging.minloglevel = old


def _extract_and_match(db: Path, image_root: Path, names: Sequence[str], opts: ColmapOptions,
                       camera_model: str = "PINHOLE", shared_intrinsics: bool = False,
                       camera_id: int | None = None) -> None:
    """Add ``names`` to the database (created if missing) and match them with every image in it.
    ``camera_id``: an existing camera (and its rig) the new images share (shared intrinsics)."""
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    if camera_id is not None:
        reader.existing_camera_id = camera_id
    # Import sequentially first so that ids are deterministic (parallel extraction would shuffle
    # them): each image gets its own camera, rig and frame, all of one id; COLMAP, not ``names``,
    # orders the ids (database_ids reads them back by name).
    pycolmap.Database.open(db).close()  # creates the database if missing
    mode = pycolmap.CameraMode.SINGLE if shared_intrinsics else pycolmap.CameraMode.PER_IMAGE
    pycolmap.import_images(db, image_root, camera_mode=mode, image_names=list(names), options=reader)
    ext = pycolmap.FeatureExtractionOptions()
    ext.max_image_size = opts.max_image_size
    ext.num_threads = opts.num_threads
    ext.sift.max_num_features = opts.max_num_features
    ext.sift.peak_threshold = opts.sift_peak_threshold
    pycolmap.extract_features(db, image_root, image_names=list(names), camera_mode=mode,
                              reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu)
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = opts.num_threads
    # Each pair's geometric verification is a RANSAC; unseeded, it draws from the generator of
    # whichever worker thread takes the pair, so the verified matches (and the points) changed
    # from run to run. A fixed seed makes every pair's RANSAC the same on any thread count.
    verify = pycolmap.TwoViewGeometryOptions()
    verify.ransac.random_seed = RANDOM_SEED
    # pairs already in the database (an earlier call's) are not matched again
    pycolmap.match_exhaustive(db, matching_options=matching, verification_options=verify,
                              device=pycolmap.Device.cpu)


def triangulate_known_poses(image_root: Path, image_names: Sequence[str], cameras: Sequence[Camera],
                            work_dir: Path, opts: ColmapOptions = ColmapOptions()) -> tuple[np.ndarray, np.ndarray]:
    """Sparse points seen by the given posed, undistorted images.

    ``image_names[i]`` (relative to ``image_root``) was taken by ``cameras[i]``.
    Returns xyz (P,3) float64 and rgb (P,3) uint8.
    """
    import pycolmap

    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    db_path = work_dir / "database.db"
    if db_path.exists():
        db_path.unlink()
    with _quiet_glog(image_root):
        _extract_and_match(db_path, image_root, image_names, opts)
        ids = database_ids(db_path, image_names, image_root)
        rec = pycolmap.Reconstruction()
        for name, cam, (image_id, camera_id) in zip(image_names, cameras, ids):
            rec.add_camera_with_trivial_rig(colmap_camera_of(cam, camera_id))
            img = pycolmap.Image(name=name, camera_id=camera_id, image_id=image_id)
            rec.add_image_with_trivial_frame(img, rigid3d_of(cam))
        popts = pycolmap.IncrementalPipelineOptions()
        popts.triangulation.min_angle = opts.min_tri_angle
        popts.triangulation.ignore_two_view_tracks = not opts.two_view_tracks
        popts.num_threads = opts.num_threads
        popts.random_seed = RANDOM_SEED
        out_dir = work_dir / "model"
        out_dir.mkdir(exist_ok=True)
        rec = pycolmap.triangulate_points(rec, db_path, image_root, out_dir, clear_points=True, options=popts,
                                          refine_intrinsics=False)
    xyz, rgb = [], []
    for p in rec.points3D.values():
        if p.track.length() >= opts.min_track_length and p.error <= opts.max_reproj_error:
            xyz.append(p.xyz)
            rgb.append(p.color)
    if not xyz:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    return np.array(xyz, np.float64), np.array(rgb, np.uint8)


def verified_pairs(image_root: Path, names: Sequence[str], db_path: Path,
                   opts: ColmapOptions = ColmapOptions()) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
    """SIFT matches of every pair of ``names`` that COLMAP's two-view RANSAC verified (it knows
    nothing of any poses): (i, j, xy_i (N,2), xy_j (N,2)) with i < j indices into ``names``,
    pixel positions with pixel centres at +0.5, as ours."""
    import pycolmap

    out = []
    with _quiet_glog(image_root):
        _extract_and_match(db_path, image_root, names, opts)
        ids = [i for i, _ in database_ids(db_path, names, image_root)]
        db = pycolmap.Database.open(db_path)
        try:
            xy = [np.asarray(db.read_keypoints(i))[:, :2] for i in ids]
            for a in range(len(ids)):
                for b in range(a + 1, len(ids)):
                    if not db.exists_two_view_geometry(ids[a], ids[b]):
                        continue
                    m = np.asarray(db.read_two_view_geometry(ids[a], ids[b]).inlier_matches).reshape(-1, 2)
                    if len(m):
                        out.append((a, b, xy[a][m[:, 0]], xy[b][m[:, 1]]))
        finally:
            db.close()
    return out


def database_ids(db_path: Path, names: Sequence[str], image_root: Path) -> list[tuple[int, int]]:
    """(image id, camera id) in the COLMAP database of each of ``names``, looked up by name: the
    database numbers images in COLMAP's order (names sorted as strings), not in ``names``' order.
    Each image must be the only image of its frame, on its camera's own rig (what importing one
    camera per image makes), because the reconstruction's trivial frames and rigs take those ids."""
    import pycolmap

    db = pycolmap.Database.open(db_path)
    try:
        by_name = {img.name: img for img in db.read_all_images()}
        rig_of = {f.frame_id: f.rig_id for f in db.read_all_frames()}
    finally:
        db.close()
    out = []
    for name in names:
        img = by_name.get(name)
        if img is None:
            raise DataError(f"{image_root / name}: COLMAP could not read this image")
        if img.frame_id != img.image_id or rig_of.get(img.frame_id) != img.camera_id:
            raise RuntimeError(f"COLMAP database frame of {name} is not a trivial frame of its own camera")
        out.append((img.image_id, img.camera_id))
    return out


def sfm_static_cameras(image_root: Path, image_names: Sequence[str], camera_names: Sequence[str],
                       work_dir: Path, opts: ColmapOptions = ColmapOptions(),
                       camera_model: str = "SIMPLE_RADIAL", shared_intrinsics: bool = True,
                       source: str | Path | None = None, held_out: Sequence[str] = ()) -> list[Camera]:
    """Poses and intrinsics of static cameras from one image each (incremental SfM).

    With one image per camera the focal length of each camera is weakly constrained, so by
    default all cameras share one intrinsic model (typical of a capture rig of identical
    cameras); ``shared_intrinsics=False`` estimates one model per camera.

    Nothing about a held-out camera (``held_out``, camera names) may change what training uses,
    so two passes: SfM on the training cameras' images alone (the database holds nothing else
    yet), then each held-out image is added and registered against that reconstruction with
    the training frames and intrinsics fixed. The training cameras are pass 1's values, the
    same whatever the held-out images show, or whether there are any.

    Every camera must register, else a :class:`DataError` names the ones that failed. Errors
    name ``source`` (the user's capture), else ``image_root``.
    """
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    db_path = work_dir / "database.db"
    if db_path.exists():
        db_path.unlink()
    where = image_root if source is None else source
    held = set(held_out)
    train = [(n, cn) for n, cn in zip(image_names, camera_names) if cn not in held]
    test = [(n, cn) for n, cn in zip(image_names, camera_names) if cn in held]
    with _quiet_glog(image_root):
        _extract_and_match(db_path, image_root, [n for n, _ in train], opts, camera_model, shared_intrinsics)
        models = _incremental_mapping(db_path, image_root, work_dir / "sparse", opts)
    if not models:
        raise DataError(f"{where}: structure-from-motion found no model from the first frames; "
                        "the cameras need overlapping, textured views (or provide poses)")
    rec = max(models.values(), key=lambda r: r.num_reg_images())
    cams = _registered(rec, train)
    missing = [cn for n, cn in train if n not in cams]
    if missing:
        raise DataError(f"{where}: SfM could not register camera(s) {', '.join(missing)}; "
                        "they need more overlap with the others (or provide poses)")
    if test:
        cams.update(_register_held_out(db_path, image_root, rec, train, test, work_dir, opts, camera_model,
                                       shared_intrinsics, where))
    return [cams[n] for n in image_names]


def _incremental_mapping(db_path: Path, image_root: Path, out_dir: Path, opts: ColmapOptions,
                         input_path: Path | None = None, constant_cameras: Sequence[int] = ()) -> dict:
    import pycolmap

    popts = pycolmap.IncrementalPipelineOptions()
    popts.num_threads = opts.num_threads
    popts.random_seed = RANDOM_SEED
    popts.multiple_models = False
    if input_path is not None:  # continue a model: its frames and the given cameras' intrinsics stay
        popts.fix_existing_frames = True
        popts.constant_cameras = set(constant_cameras)
    out_dir.mkdir(parents=True, exist_ok=True)
    return pycolmap.incremental_mapping(db_path, image_root, out_dir, options=popts,
                                        input_path="" if input_path is None else input_path)


def _registered(rec, named: Sequence[tuple[str, str]]) -> dict[str, Camera]:
    """Camera of each (image name, camera name) registered in ``rec``, by image name."""
    by_name = {img.name: img for img in rec.images.values() if img.has_pose}
    return {n: camera_from_colmap(rec.cameras[by_name[n].camera_id], by_name[n].cam_from_world(), cn)
            for n, cn in named if n in by_name}


def _register_held_out(db_path: Path, image_root: Path, rec, train: Sequence[tuple[str, str]],
                       test: Sequence[tuple[str, str]], work_dir: Path, opts: ColmapOptions, camera_model: str,
                       shared_intrinsics: bool, where) -> dict[str, Camera]:
    """Pass 2: the held-out images registered into the training reconstruction ``rec`` (left as it
    is), their cameras in ``rec``'s frame."""
    import pycolmap

    train_dir = work_dir / "sparse_train"
    train_dir.mkdir(parents=True, exist_ok=True)
    rec.write(train_dir)
    train_cams = sorted({img.camera_id for img in rec.images.values() if img.has_pose})
    with _quiet_glog(image_root):
        _extract_and_match(db_path, image_root, [n for n, _ in test], opts, camera_model, shared_intrinsics,
                           camera_id=train_cams[0] if shared_intrinsics else None)
        models = _incremental_mapping(db_path, image_root, work_dir / "sparse_held_out", opts,
                                      input_path=train_dir, constant_cameras=train_cams)
    rec2 = max(models.values(), key=lambda r: r.num_reg_images()) if models else None
    cams = _registered(rec2, test) if rec2 is not None else {}
    missing = [cn for n, cn in test if n not in cams]
    if missing:
        raise DataError(f"{where}: SfM could not register held-out camera(s) {', '.join(missing)} against the "
                        "training cameras; hold out another camera (--test-cams) or provide poses")
    # COLMAP's global refinement re-normalizes the model it continues (shifts and scales it, fixed
    # frames included; by ~1e-15 on the test rig): back to pass 1's frame, fitted on the training cameras
    s, R, t = _similarity(list(_registered(rec2, train).values()), list(_registered(rec, train).values()))
    rec2.transform(pycolmap.Sim3d(s, pycolmap.Rotation3d(R), t))
    return _registered(rec2, test)


def _similarity(src: Sequence[Camera], dst: Sequence[Camera]) -> tuple[float, np.ndarray, np.ndarray]:
    """s, R, t with dst's world = s R (src's world) + t, for the same rigid set of cameras posed in
    two worlds (two cameras suffice, where Umeyama on the centers needs three)."""
    cs, cd = np.array([c.center for c in src]), np.array([c.center for c in dst])
    s = np.linalg.norm(cd - cd.mean(0)) / np.linalg.norm(cs - cs.mean(0))
    R = dst[0].R.T @ src[0].R  # cam_from_world rotations: R_src = R_dst R
    return float(s), R, cd.mean(0) - s * R @ cs.mean(0)
