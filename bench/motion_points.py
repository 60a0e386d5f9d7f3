"""Moving-content points (atgs.data.moving_points) on every synthetic layout: accuracy and time.

For each layout of atgs.data.synth.scene.LAYOUTS (large motion, plus the small-motion front rig)
a 30-frame scene is synthesized and prepared without stereo (SIFT only: the motion points do not
depend on it) with 3 geometry keyframes, so 9 motion keyframes. At each motion keyframe the
motion points are compared with the true moving meshes:

- precision: median distance of the points to the nearest moving surface, in % of the scene
  size, and the share of points within 3 % of it;
- recall: the share of points sampled on the moving surfaces (area-weighted, hidden sides
  included) that have a motion point within 3 % of the scene size.

    python bench/motion_points.py            # writes bench/results/motion_points.json, docs/data.md table
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _docs import git_commit, publish  # noqa: E402

from atgs.data.moving_points import MotionPointsConfig  # noqa: E402
from atgs.data.mvs import StereoConfig  # noqa: E402
from atgs.data.prepare import PrepareConfig, prepare  # noqa: E402
from atgs.data.scene import PreparedScene  # noqa: E402
from atgs.data.synth.videos import load_ground_truth, synthesize  # noqa: E402
from atgs.data.synth.scene import LAYOUTS, SynthConfig, distance_to_surfaces, sample_surface  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CASES = [("ring12", "large-motion"), ("ring10-low", "large-motion"), ("front6", "large-motion"),
         ("front6", "small-motion"), ("ring12-flat", "large-motion")]


def run_case(tmp: Path, layout: str, preset: str, frames: int, select: str = "photo") -> dict:
    cfg = replace(SynthConfig(frames=frames, preset=preset), **LAYOUTS[layout])
    raw = synthesize(tmp / f"{layout}-{preset}", cfg, progress=False, overwrite=True)
    out = prepare(PrepareConfig(src=raw, out=tmp / f"{layout}-{preset}-prep", keyframes=3, overwrite=True,
                                progress=False, stereo=StereoConfig(enabled=False),
                                motion=MotionPointsConfig(select=select)))
    s = PreparedScene.load(out)
    gt = load_ground_truth(raw)
    size = gt.cfg.scene_size
    tol = 0.03 * size
    rng = np.random.default_rng(0)
    prec, near, rec, npts = [], [], [], []
    for j, f in enumerate(s.motion_keyframes):
        pts = s.motion_cloud.read(j).astype(np.float64)
        npts.append(len(pts))
        if len(pts) == 0:
            continue
        d = distance_to_surfaces(gt, f, pts[:: max(1, len(pts) // 400)], moving_only=True)
        prec.append(float(np.median(d)) / size * 100)
        near.append(float((d < tol).mean()))
        samples = sample_surface(gt, f, 400, rng, moving_only=True)
        dd = np.sqrt(((samples[:, None, :] - pts[None, :, :]) ** 2).sum(-1)).min(1)
        rec.append(float((dd < tol).mean()))
    import json
    meta = json.loads((out / "scene.json").read_text())
    return {"layout": layout, "preset": preset, "cameras": cfg.cameras, "size": [cfg.width, cfg.height],
            "frames": frames, "motion_keyframes": len(s.motion_keyframes), "points_per_keyframe": npts,
            "median_distance_pct": prec, "within_3pct": near, "recall_3pct": rec,
            "moving_fraction": meta["motion_points"]["moving_fraction"],
            "seconds": meta["source"]["timings_s"].get("motion_points")}


def table(res: dict) -> str:
    lines = ["| layout | motion | cams | motion keyframes | points / keyframe | median distance to the moving surfaces, "
             "% of scene size | points within 3 % | moving surface within 3 % of a point | seconds |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in res["cases"]:
        if not r["median_distance_pct"]:
            lines.append(f"| {r['layout']} | {r['preset']} | {r['cameras']} | 0 | 0 | | | | {r['seconds']} |")
            continue
        rng = lambda v, f: f"{f(min(v))}-{f(max(v))}"  # noqa: E731
        lines.append(f"| {r['layout']} | {r['preset']} | {r['cameras']} | {r['motion_keyframes']} | "
                     f"{int(np.mean(r['points_per_keyframe'])):,} | "
                     f"{rng(r['median_distance_pct'], lambda x: f'{x:.2f}')} | "
                     f"{rng(r['within_3pct'], lambda x: f'{x:.0%}')} | {rng(r['recall_3pct'], lambda x: f'{x:.0%}')} | "
                     f"{r['seconds']} |")
    lines.append("")
    lines.append(f"{res['frames']} frames, 3 geometry keyframes (SIFT only) -> 9 motion keyframes; ranges over the "
                 f"motion keyframes; {res['date']}, load {res['load'][0]}-{res['load'][1]}; "
                 "`python bench/motion_points.py`.")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "motion_points.json")
    ap.add_argument("--docs", type=Path, default=ROOT / "docs" / "data.md")
    ap.add_argument("--only", nargs="*", help="layouts to run (a check; default: all, and the results are written)")
    ap.add_argument("--select", default="photo", help="MotionPointsConfig.select")
    a = ap.parse_args()
    l0 = round(os.getloadavg()[0], 2)
    cases = []
    with tempfile.TemporaryDirectory() as tmp:
        for layout, preset in CASES:
            if a.only and layout not in a.only:
                continue
            t = time.perf_counter()
            cases.append(run_case(Path(tmp), layout, preset, a.frames, a.select))
            print(f"{layout}/{preset}: {time.perf_counter() - t:.0f} s", file=sys.stderr)
    res = {"cases": cases, "frames": a.frames, "date": time.strftime("%Y-%m-%d"),
           "load": [l0, round(os.getloadavg()[0], 2)], "commit": git_commit(ROOT),
           "machine": {"cpus": os.cpu_count(), "python": platform.python_version()}}
    res["select"] = a.select
    if a.only:
        print(table(res))
        return
    publish(res, a.out, table(res), a.docs, "motion-points")


if __name__ == "__main__":
    main()
