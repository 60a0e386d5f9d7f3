"""The README's main job, measured: what `./scripts/demo.sh` runs and prints.

    python bench/demo.py                      # fresh cache: synthesize + prepare + train (default preset)
    python bench/demo.py --reuse-cache        # keep the built-in scene from an earlier run
    python bench/demo.py -- --preset cpu-fast # extra arguments go to atgs-train

It runs `atgs-train --out WORK/demo` with the same defaults as the demo (the built-in
large-motion scene, preset `cpu`, its 20-minute budget), reads the run's result.json (the
held-out figure atgs-train prints at the end, which is atgs-eval's default evaluation) and
writes bench/results/demo.json. bench/readme_table.py turns it into the README row.
"""

from __future__ import annotations

import json
import math
import os
import platform
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import tyro
from _docs import git_commit  # bench/_docs.py (the script's own folder is on sys.path)

from atgs.io.atomic import write_json_atomic

ROOT = Path(__file__).resolve().parent.parent


@dataclass
class DemoBench:
    work_dir: Path = Path("/tmp/atgs-bench-demo")
    """Run folder and (unless --reuse-cache) a fresh cache for the built-in scene."""
    reuse_cache: bool = False
    """Use $ATGS_CACHE_DIR (else ~/.cache/atgs) instead of a fresh cache in the work folder."""
    out: Path = ROOT / "bench" / "results" / "demo.json"
    train_args: tuple[str, ...] = field(default_factory=tuple)
    """Extra atgs-train arguments (after --)."""


def moving_static_psnr(ckpt: Path, scene_dir: Path, every: int = 8) -> dict:
    """Held-out PSNR on the pixels that move and on the rest: a pixel moves at a frame when it
    differs from its camera's background (atgs.data.motion_points.motion_mask at full size)."""
    import numpy as np
    import torch

    import atgs
    from atgs.data.motion import box_downsample
    from atgs.data.motion_points import MotionPointsConfig, background, motion_mask
    from atgs.data.scene import PreparedScene
    from atgs.render import rasterize_gaussians
    from atgs.timeline import evenly_spaced

    scene, model, cfg = PreparedScene.load(scene_dir), atgs.load(ckpt), MotionPointsConfig()
    se, n = {True: 0.0, False: 0.0}, {True: 0, False: 0}
    for ci in scene.test_indices:
        side = max(scene.cameras[ci].width, scene.cameras[ci].height)
        bg = background([box_downsample(scene.image_uint8(ci, f), side) for f in evenly_spaced(scene.num_frames, 48)])
        for f in range(0, scene.num_frames, every):
            gt = scene.image_uint8(ci, f)
            mask = motion_mask(box_downsample(gt, side), bg, cfg)
            with torch.no_grad():
                img = rasterize_gaussians(model.gaussians_at_frame(f), scene.cameras[ci]).image.clamp(0, 1).numpy()
            err = ((img - gt.astype(np.float32) / 255.0) ** 2).mean(-1)
            for moving in (True, False):
                sel = mask == moving
                se[moving] += float(err[sel].sum())
                n[moving] += int(sel.sum())
    db = lambda k: round(-10 * math.log10(se[k] / max(n[k], 1)), 2) if n[k] else None  # noqa: E731
    return {"psnr_moving": db(True), "psnr_static": db(False),
            "moving_fraction": round(n[True] / max(n[True] + n[False], 1), 4), "every_nth_frame": every}


def main() -> None:
    argv = sys.argv[1:]
    extra: list[str] = []
    if "--" in argv:
        i = argv.index("--")
        argv, extra = argv[:i], argv[i + 1:]
    args = tyro.cli(DemoBench, args=argv)
    run = args.work_dir / "demo"
    if run.exists():
        shutil.rmtree(run)
    env = dict(os.environ)
    if not args.reuse_cache:
        cache = args.work_dir / "cache"
        shutil.rmtree(cache, ignore_errors=True)
        env["ATGS_CACHE_DIR"] = str(cache)
        # the compiled rasterizer is not what this bench measures: keep its build
        build = Path(os.environ.get("ATGS_CACHE_DIR", Path.home() / ".cache" / "atgs"))
        for d in build.glob("torch_extensions*"):
            shutil.copytree(d, cache / d.name, dirs_exist_ok=True)
    cmd = [sys.executable, "-m", "atgs.cli.train", "--out", str(run), *args.train_args, *extra]
    load_before = os.getloadavg()
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, stdout=subprocess.PIPE, text=True)
    wall = time.perf_counter() - t0
    print(proc.stdout)
    if proc.returncode != 0:
        sys.exit(f"bench/demo.py: atgs-train failed with exit code {proc.returncode}")
    res = json.loads((run / "result.json").read_text())
    last = [ln for ln in proc.stdout.splitlines() if "done," in ln]
    out = {
        "command": " ".join(["atgs-train --out runs/demo", *args.train_args, *extra]),
        "printed": last[-1] if last else "",
        "psnr": res["eval"]["psnr"], "ssim": res["eval"]["ssim"], "eval_views": res["eval"]["views"],
        "steps": res["steps"], "train_seconds": res["seconds"], "wall_seconds": wall,
        "fresh_cache": not args.reuse_cache,
        "budget_seconds": res.get("budget_seconds"), "seconds_per_step": res.get("seconds_per_step"),
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "loadavg_before": list(load_before), "loadavg_after": list(os.getloadavg())},
        "commit": git_commit(ROOT), "date": time.strftime("%Y-%m-%d"),
    }
    scenes = sorted((Path(env.get("ATGS_CACHE_DIR", Path.home() / ".cache" / "atgs"))).glob("synth-*/prepared-v*"))
    if scenes and not extra and not args.train_args:  # the built-in scene the run trained on
        out["split"] = moving_static_psnr(run / "ckpt.pt", scenes[-1])
    write_json_atomic(args.out, out, indent=2)
    print(f"wrote {args.out}: held-out PSNR {out['psnr']:.2f} dB, SSIM {out['ssim']:.4f}, "
          f"{out['steps']} steps, {wall / 60:.1f} min wall")


if __name__ == "__main__":
    main()
