"""Oracle keyframe points for a prepared synthetic scene: the true depth back-projected.

For the "oracle gap" experiment: train once from the stereo points and once from points of the
true geometry, everything else equal. :func:`oracle_points` renders the true depth of every
training camera at each keyframe with the mesh renderer (at the stereo's working resolution),
back-projects every pixel, colours it from the prepared frame, and voxel-averages with the same
rule as the stereo (:class:`atgs.data.mvs.StereoConfig` ``voxel_px`` and ``max_points``).
:func:`make_oracle_scene` writes a copy of the prepared scene whose points.ply holds them (same
frames, cameras, keyframes and bounds).

    python -m atgs.data.oracle PREPARED --out PREPARED_ORACLE
"""

from __future__ import annotations

import json
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import tyro
from PIL import Image

from atgs.data.errors import DataError
from atgs.data.mvs import StereoConfig
from atgs.data.mvs.fusion import capped_voxel_average
from atgs.data.scene import MemoryScene, PreparedScene, write_scene_metadata
from atgs.geometry.coverage import scene_coverage, working_camera
from atgs.geometry.rays import pixel_rays, to_world
from atgs.io.atomic import atomic_dir, link_or_copy


def source_frame(scene: PreparedScene, frame: int) -> int:
    """The synthetic scene's frame index of a prepared frame (the prepare step's frame selection)."""
    start, _, step = scene.source.get("frames", [0, None, 1])
    return int(start) + int(frame) * int(step)


def oracle_points(scene: PreparedScene, stereo: StereoConfig = StereoConfig(),
                  include_test: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points (P,3) float64, colours (P,3) uint8 and keyframe indices (P,) from the true depth."""
    from atgs.data.synth.videos import load_ground_truth
    from atgs.data.synth.mesh_renderer import MeshRenderer

    side = scene.root / "synth.json"
    if not side.is_file():
        raise DataError(f"{side}: not found; oracle points need a scene prepared from atgs-synth output")
    gt = load_ground_truth(side)
    idx = list(range(len(scene.cameras))) if include_test else scene.train_indices
    wcams = [working_camera(scene.cameras[i], stereo.long_side) for i in idx]
    renderers: dict[tuple[int, int], MeshRenderer] = {}
    P, C, K = [], [], []
    try:
        for j, f in enumerate(scene.keyframes):
            pts, cols, depths = [], [], []
            for i, cam in zip(idx, wcams):
                key = (cam.width, cam.height)
                if key not in renderers:
                    renderers[key] = MeshRenderer(gt, *key)
                r = renderers[key]
                r.set_frame(source_frame(scene, f))
                d = r.render_depth(cam)
                img = scene.image_uint8(i, f)
                if img.shape[:2] != d.shape:
                    img = np.asarray(Image.fromarray(img).resize(key, Image.BOX))
                v, u = np.nonzero(d > 0)
                z = d[v, u].astype(np.float64)
                pts.append(to_world(cam, pixel_rays(cam, u + 0.5, v + 0.5) * z[:, None]))
                cols.append(img[v, u].astype(np.float32) / 255.0)
                depths.append(np.median(z) / np.sqrt(cam.fx * cam.fy) if len(z) else 0.0)
            voxel = stereo.voxel_px * float(np.median(depths))
            p, c, _ = capped_voxel_average(np.concatenate(pts), np.concatenate(cols), voxel, stereo.max_points)
            P.append(p)
            C.append(np.clip(np.round(c * 255), 0, 255).astype(np.uint8))
            K.append(np.full(len(p), j, np.int64))
    finally:
        for r in renderers.values():
            r.release()
    return np.concatenate(P), np.concatenate(C), np.concatenate(K)


def make_oracle_scene(prepared: Path, out: Path, stereo: StereoConfig = StereoConfig(),
                      overwrite: bool = False) -> Path:
    """A copy of ``prepared`` (frames hard-linked where possible) whose points are the oracle's."""
    scene = PreparedScene.load(prepared)
    pts, cols, kf = oracle_points(scene, stereo)
    meta = json.loads((Path(prepared) / "scene.json").read_text())
    with atomic_dir(Path(out), overwrite) as tmp:
        shutil.copytree(Path(prepared) / "images", tmp / "images", copy_function=link_or_copy)
        shutil.copy2(Path(prepared) / "synth.json", tmp / "synth.json")
        if (Path(prepared) / "motion_points.ply").is_file():  # the moving-content points stay as they are
            shutil.copy2(Path(prepared) / "motion_points.ply", tmp / "motion_points.ply")
        cov = scene_coverage(scene.cameras, pts, kf, len(scene.keyframes), scene.test_cameras, stereo.long_side)
        source = dict(scene.source, oracle={"from": str(Path(prepared).resolve()), "points": int(len(pts))})
        content = MemoryScene(scene.cameras, scene.num_frames, scene.fps, scene.keyframes, pts, kf, scene.test_cameras,
                              bounds=scene.bounds, point_colors=cols)
        write_scene_metadata(tmp, content, name=scene.name, source=source,
                             extra={"coverage": cov, "keyframe_points": {"oracle": np.bincount(
                                 kf, minlength=len(scene.keyframes)).tolist()},
                                 **{k: v for k, v in meta.items() if k not in _WRITTEN}})
    return Path(out)


_WRITTEN = {"format", "version", "name", "fps", "num_frames", "cameras", "test_cameras", "keyframes", "bounds",
            "source", "coverage", "keyframe_points"}



@dataclass(frozen=True)
class OracleArgs:
    prepared: Annotated[Path, tyro.conf.Positional]
    """A scene prepared by atgs-prepare from atgs-synth output (it holds synth.json)."""
    out: Path
    """The copy with oracle points."""
    stereo: StereoConfig = StereoConfig()
    """Working resolution and voxel rule (the same as the stereo's, so only the points differ)."""
    overwrite: bool = False


def main(argv: list[str] | None = None) -> int:
    a = tyro.cli(OracleArgs, args=argv, description=__doc__)
    try:
        out = make_oracle_scene(a.prepared, a.out, a.stereo, a.overwrite)
    except DataError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"oracle scene written to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
