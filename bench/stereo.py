"""Keyframe geometry benchmark: CPU PatchMatch stereo against SIFT triangulation alone, on every
synthetic layout and on the real N3DV frame.

For each synthetic layout (atgs.data.synth.scene.LAYOUTS x motion preset) a 2-frame scene is
synthesized and prepared at one keyframe (frame 0, cam00 held out) twice: with stereo (the
default) and with ``--no-stereo --no-fill`` (SIFT alone). Reported: points per keyframe, their
median / 90th-percentile distance to the true surfaces (% of the scene size, the camera ring's
diameter), the coverage of the held-out cam00 and the training cameras' mean coverage
(docs/data.md defines coverage), the oracle coverage (true depth back-projected: the ceiling),
and the fill points. Then the stereo time for one keyframe of 12 cameras at 256x192 (repeated;
the 1-minute load average is recorded beside it), and the real N3DV frame prepared at
--downscale 4 with cam00 held out.

Run by hand:  PYTHONPATH=. python bench/stereo.py [--quick] [--only LAYOUT ...] [--no-n3dv] [--timing-only]
Writes bench/results/stereo.json and the table in docs/data.md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from atgs.data.mvs import FillConfig, StereoConfig, stereo_points  # noqa: E402
from atgs.data.oracle import oracle_points  # noqa: E402
from atgs.data.prepare import PrepareConfig, prepare  # noqa: E402
from atgs.data.scene import PreparedScene  # noqa: E402
from atgs.data.synth.scene import LAYOUTS, SynthConfig, SynthScene, distance_to_surfaces  # noqa: E402
from atgs.data.synth.videos import synthesize  # noqa: E402
from atgs.geometry.coverage import scene_coverage  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
N3DV = ROOT.parent / "shared" / "data" / "n3dv_flame_steak_frame0"
CASES = [("ring12", "large-motion"), ("ring12", "small-motion"), ("ring10-low", "large-motion"),
         ("front6", "small-motion"), ("front6", "large-motion"), ("ring12-flat", "large-motion")]


def load() -> float:
    return round(os.getloadavg()[0], 2)


def surface_stats(scene: SynthScene, pts: np.ndarray, size: float, n: int = 2000) -> dict:
    if len(pts) == 0:
        return {"median_pct": None, "p90_pct": None}
    sel = pts[np.random.default_rng(0).permutation(len(pts))[:n]]
    d = distance_to_surfaces(scene, 0, sel)
    return {"median_pct": round(100 * float(np.median(d)) / size, 3), "p90_pct": round(100 * float(np.percentile(d, 90)) / size, 3)}


def prepared_stats(out: Path, gt: SynthScene) -> dict:
    s = PreparedScene.load(out)
    meta = json.loads((out / "scene.json").read_text())
    counts, cov = meta["keyframe_points"], meta["coverage"]
    n_fill = counts["fill"][0]
    measured = s.points[: len(s.points) - n_fill] if n_fill else s.points  # fill points are written last
    return {"points": int(len(measured)), "sift": counts["sift"][0], "stereo": counts["stereo"][0], "fill": n_fill,
            **surface_stats(gt, measured, gt.cfg.scene_size),
            "coverage_cam00": cov["test_cameras"].get("cam00"), "coverage_train_mean": cov["mean"],
            "points_s": s.source["timings_s"]["points"]}


def synthetic_case(tmp: Path, layout: str, preset: str) -> dict:
    cfg = replace(SynthConfig(frames=2, preset=preset), **LAYOUTS[layout])
    raw = synthesize(tmp / f"{layout}-{preset}", cfg, progress=False, overwrite=True)
    gt = SynthScene(cfg)
    row: dict = {"layout": layout, "preset": preset, "cameras": cfg.cameras, "size": [cfg.width, cfg.height]}
    t = time.perf_counter()
    out = prepare(PrepareConfig(src=raw, out=tmp / "stereo", keyframes=1, overwrite=True, progress=False))
    row["stereo"] = {**prepared_stats(out, gt), "prepare_s": round(time.perf_counter() - t, 1), "load": load()}
    ref = PreparedScene.load(out)
    opts, okf = oracle_points(ref)[0::2]
    row["oracle_coverage_cam00"] = scene_coverage(ref.cameras, opts, okf, 1, ["cam00"])["test_cameras"]["cam00"]
    t = time.perf_counter()
    out = prepare(PrepareConfig(src=raw, out=tmp / "sift", keyframes=1, overwrite=True, progress=False,
                                stereo=StereoConfig(enabled=False), fill=FillConfig(enabled=False)))
    row["sift_only"] = {**prepared_stats(out, gt), "prepare_s": round(time.perf_counter() - t, 1)}
    print(json.dumps(row), flush=True)
    return row


def stereo_timing(tmp: Path, repeats: int) -> dict:
    """Stereo alone (no SIFT) for one keyframe of the 12 cameras of the default scene at 256x192."""
    from atgs.data.synth.mesh_renderer import MeshRenderer

    cfg = SynthConfig(frames=1)
    gt = SynthScene(cfg)
    r = MeshRenderer(gt, cfg.width, cfg.height)
    r.set_frame(0)
    cams = gt.cameras()
    imgs = [r.render(c) for c in cams]
    r.release()
    seeds = oracle_seed(gt, cams)
    runs = []
    for _ in range(repeats):
        before = load()
        t = time.perf_counter()
        res = stereo_points(imgs, cams, StereoConfig(), seed_points=seeds)
        runs.append({"seconds": round(time.perf_counter() - t, 1), "load_before": before, "load_after": load(),
                     "points": int(len(res.points)), "steps_s": {k: round(v, 1) for k, v in res.seconds.items()}})
        print(json.dumps(runs[-1]), flush=True)
    return {"cameras": len(cams), "size": [cfg.width, cfg.height], "runs": runs, "cpus": os.cpu_count()}


def oracle_seed(gt: SynthScene, cams) -> np.ndarray:
    """~1000 SIFT-like seed points (true surface points seen by the cameras) for the timing run."""
    from atgs.data.synth.scene import sample_surface

    return sample_surface(gt, 0, 1000, max_radius=6.4)


def n3dv_case(tmp: Path) -> dict:
    row: dict = {"source": str(N3DV), "downscale": 4, "test": "cam00"}
    for name, kw in (("stereo", {}), ("sift_only", {"stereo": StereoConfig(enabled=False), "fill": FillConfig(enabled=False)})):
        t = time.perf_counter()
        before = load()
        out = prepare(PrepareConfig(src=N3DV, out=tmp / f"n3dv-{name}", downscale=4.0, test_cams=("0",), keyframes=1,
                                    overwrite=True, progress=False, **kw))
        meta = json.loads((out / "scene.json").read_text())
        row[name] = {"points": meta["keyframe_points"], "coverage_cam00": meta["coverage"]["test_cameras"]["cam00"],
                     "coverage_train_mean": meta["coverage"]["mean"], "prepare_s": round(time.perf_counter() - t, 1),
                     "points_s": meta["source"]["timings_s"]["points"], "load_before": before, "load_after": load()}
        print(json.dumps({name: row[name]}), flush=True)
    return row


def table(res: dict) -> str:
    lines = ["| layout | preset | cams | points/kf stereo+SIFT (SIFT alone) | median / p90 distance, % of scene size: "
             "stereo (SIFT) | cam00 coverage: stereo (SIFT) [true depth] | train coverage: stereo (SIFT) | fill | "
             "prepare 1 kf s |", "|---|---|---|---|---|---|---|---|---|"]
    for r in res["synthetic"]:
        s, b = r["stereo"], r["sift_only"]
        f = lambda x: "-" if x is None else f"{x:.2f}"  # noqa: E731
        lines.append(f"| {r['layout']} | {r['preset']} | {r['cameras']} | {s['points']:,} ({b['points']:,}) | "
                     f"{f(s['median_pct'])} / {f(s['p90_pct'])} ({f(b['median_pct'])} / {f(b['p90_pct'])}) | "
                     f"{s['coverage_cam00']:.0%} ({b['coverage_cam00']:.0%}) [{r['oracle_coverage_cam00']:.0%}] | "
                     f"{s['coverage_train_mean']:.0%} ({b['coverage_train_mean']:.0%}) | {s['fill']:,} | {s['prepare_s']} |")
    if "timing" in res:
        t = res["timing"]
        secs = [x["seconds"] for x in t["runs"]]
        loads = [x["load_before"] for x in t["runs"]]
        lines.append(f"\nStereo alone, one keyframe of {t['cameras']} cameras at {t['size'][0]}x{t['size'][1]}: "
                     f"{', '.join(f'{x:.1f}' for x in secs)} s ({len(secs)} runs; 1-minute load average "
                     f"{min(loads):.1f}-{max(loads):.1f} on {t['cpus']} cores); target 30 s.")
    if "n3dv" in res:
        n = res["n3dv"]
        s, b = n["stereo"], n["sift_only"]
        pts = lambda m: sum(m["points"].get("stereo", [0])) + sum(m["points"].get("sift", [0]))  # noqa: E731
        lines.append(f"\nN3DV flame_steak frame 0, --downscale 4 (672x504), cam00 held out: cam00 coverage "
                     f"{s['coverage_cam00']:.0%} with stereo ({pts(s):,} points, {s['points_s']:.0f} s) vs "
                     f"{b['coverage_cam00']:.0%} with SIFT alone ({pts(b):,} points, {b['points_s']:.0f} s); training "
                     f"cameras {s['coverage_train_mean']:.0%} vs {b['coverage_train_mean']:.0%}.")
    return "\n".join(lines)


def main() -> None:
    from bench._docs import update_docs_table, write_json_atomic

    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="one layout, one timing run, no N3DV")
    ap.add_argument("--only", nargs="*", help="layouts to run (default: all)")
    ap.add_argument("--no-n3dv", action="store_true")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-write", action="store_true", help="print only")
    ap.add_argument("--timing-only", action="store_true",
                    help="re-run only the timing (e.g. when the machine is quieter) into the existing results")
    a = ap.parse_args()
    out = ROOT / "bench" / "results" / "stereo.json"
    if a.timing_only:
        res = json.loads(out.read_text())
        with tempfile.TemporaryDirectory(prefix="bench-stereo-") as tmp:
            res["timing"] = stereo_timing(Path(tmp), a.repeats)
        print(table(res))
        if not a.no_write:
            write_json_atomic(out, res)
            update_docs_table(ROOT / "docs" / "data.md", "stereo", table(res))
        return
    cases = [c for c in CASES if not a.only or c[0] in a.only]
    if a.quick:
        cases = cases[:1]
    res: dict = {"machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
                 "stereo_config": StereoConfig().__dict__, "fill_config": FillConfig().__dict__, "synthetic": []}
    with tempfile.TemporaryDirectory(prefix="bench-stereo-") as tmp:
        tmp = Path(tmp)
        for layout, preset in cases:
            res["synthetic"].append(synthetic_case(tmp, layout, preset))
        res["timing"] = stereo_timing(tmp, 1 if a.quick else a.repeats)
        if not (a.quick or a.no_n3dv) and N3DV.is_dir():
            res["n3dv"] = n3dv_case(tmp)
    print(table(res))
    if not a.no_write:
        write_json_atomic(out, res)
        update_docs_table(ROOT / "docs" / "data.md", "stereo", table(res), create_section="Keyframe geometry: measured")


if __name__ == "__main__":
    main()
