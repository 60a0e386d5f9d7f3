"""Data pipeline benchmark: synthesis and prepare times, video round-trip PSNR, triangulation
accuracy (known poses) and SfM pose accuracy on the built-in synthetic scenes.

Run by hand:  python bench/bench_data.py [--quick]
Writes bench/results/data.json (and prints it); docs/data.md quotes the numbers.
"""

from __future__ import annotations

import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from atgs.data.align import pose_errors
from atgs.data.prepare import PrepareConfig, prepare
from atgs.data.scene import PreparedScene
from atgs.data.synth.videos import EncodeConfig, synthesize
from atgs.data.synth.mesh_renderer import MeshRenderer
from atgs.data.synth.scene import SynthConfig, SynthScene, distance_to_surfaces
from atgs.data.video import iter_frames
from atgs.io.atomic import write_json_atomic


def video_psnr(raw: Path, scene: SynthScene, cam_index: int = 1, max_frames: int = 30) -> float:
    r = MeshRenderer(scene, scene.cfg.width, scene.cfg.height)
    cam = scene.cameras()[cam_index]
    se, n = 0.0, 0
    for f, img in iter_frames(raw / f"{cam.name}.mp4", 0, max_frames):
        r.set_frame(f)
        se += float(np.mean((img.astype(np.float64) - r.render(cam)) ** 2))
        n += 1
    r.release()
    mse = se / n
    return float("inf") if mse == 0 else 10 * np.log10(255 ** 2 / mse)


def main() -> None:
    quick = "--quick" in sys.argv
    res: dict = {"machine": platform.processor() or platform.machine(), "python": platform.python_version()}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        cfg = SynthConfig(frames=30 if quick else 120)
        t = time.perf_counter()
        raw = synthesize(tmp / "raw", cfg, progress=False)
        res["default_scene"] = {"config": cfg.to_dict(), "synth_s": round(time.perf_counter() - t, 1)}
        t = time.perf_counter()
        out = prepare(PrepareConfig(src=raw, out=tmp / "prep", keyframes=6, progress=False))
        res["default_scene"]["prepare_s"] = round(time.perf_counter() - t, 1)
        s = PreparedScene.load(out)
        res["default_scene"]["prepare_steps_s"] = s.source["timings_s"]
        gt = SynthScene(cfg)
        tri = []
        for j, f in enumerate(s.keyframes):
            pts = s.point_cloud.read(j)  # stereo + SIFT: exact distances of a sample
            d = distance_to_surfaces(gt, f, pts[np.random.default_rng(j).permutation(len(pts))[:3000]])
            tri.append({"frame": f, "points": int(len(pts)), "median_m": float(np.median(d)),
                        "median_rel": float(np.median(d) / cfg.scene_size), "p90_rel": float(np.percentile(d, 90) / cfg.scene_size)})
        res["default_scene"]["triangulation"] = tri
        res["default_scene"]["scene_size_m"] = cfg.scene_size
        # video codecs: PSNR of decoded frames against the renderer
        codecs = {}
        small = SynthConfig(frames=10, cameras=2)
        small_scene = SynthScene(small)
        for name, enc in {"libx264rgb crf0 (default)": EncodeConfig(), "libx264 yuv444p crf0": EncodeConfig("libx264", 0, "yuv444p"),
                          "libx264 yuv444p crf10": EncodeConfig("libx264", 10, "yuv444p"),
                          "libx264 yuv420p crf10": EncodeConfig("libx264", 10, "yuv420p")}.items():
            d = synthesize(tmp / f"codec{len(codecs)}", small, enc, progress=False)
            codecs[name] = video_psnr(d, small_scene)
        res["video_psnr_db"] = {k: (None if np.isinf(v) else round(v, 2)) for k, v in codecs.items()}
        res["video_psnr_note"] = "null = lossless (MSE 0)"
        # SfM on a front-facing rig (no poses)
        sfm_cfg = SynthConfig(frames=1, cameras=10, width=320, height=240, arc_deg=90.0, seed=2, preset="small-motion")
        raw = synthesize(tmp / "sfm_raw", sfm_cfg, progress=False)
        (raw / "poses_bounds.npy").unlink()
        t = time.perf_counter()
        out = prepare(PrepareConfig(src=raw, out=tmp / "sfm", keyframes=1, progress=False))
        sc = PreparedScene.load(out)
        rot, pos = pose_errors(sc.cameras, SynthScene(sfm_cfg).cameras())
        res["sfm_front_facing_10cams_320x240"] = {"prepare_s": round(time.perf_counter() - t, 1),
                                                  "rot_max_deg": float(rot.max()), "rot_mean_deg": float(rot.mean()),
                                                  "pos_max_rel": float(pos.max() / sfm_cfg.scene_size),
                                                  "pos_mean_rel": float(pos.mean() / sfm_cfg.scene_size)}
    path = Path(__file__).parent / "results" / "data.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(path, res)
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
