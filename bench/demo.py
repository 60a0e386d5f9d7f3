"""The README's main job, measured: what `./scripts/demo.sh` runs and prints.

    python bench/demo.py                      # fresh cache: synthesize + prepare + train (default preset)
    python bench/demo.py --reuse-cache        # keep the built-in scene from an earlier run
    python bench/demo.py -- cpu-fast          # extra arguments go to atgs-train
    python bench/demo.py -- --device cuda     # on a GPU (written to bench/results/demo_cuda.json)

It runs `atgs-train --out WORK/demo` with the same defaults as the demo (the built-in
large-motion scene, preset `cpu`, its 20-minute budget), reads the run's result.json (the
held-out figure atgs-train prints at the end, which is atgs-eval's default evaluation) and
writes bench/results/demo.json. bench/readme_table.py turns it into the README row.
"""

from __future__ import annotations

import json
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
from _splits import held_out_splits

from atgs.io.atomic import write_json_atomic

ROOT = Path(__file__).resolve().parent.parent


@dataclass
class DemoBench:
    work_dir: Path = Path("/tmp/atgs-bench-demo")
    """Run folder and (unless --reuse-cache) a fresh cache for the built-in scene."""
    reuse_cache: bool = False
    """Use $ATGS_CACHE_DIR (else ~/.cache/atgs) instead of a fresh cache in the work folder."""
    out: Path = ROOT / "bench" / "results" / "demo.json"
    """Results file. A run on another device than the CPU goes to demo_<device>.json beside the
    default instead (the README's default-run rows are the CPU's)."""
    train_args: tuple[str, ...] = field(default_factory=tuple)
    """Extra atgs-train arguments (after --)."""
    what: str = ""
    """What this run changed (kept with its figures in previous_runs when the next run replaces it)."""


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
    device = json.loads((run / "config.json").read_text()).get("device", "cpu")
    if device != "cpu" and args.out == DemoBench.out:
        args.out = args.out.with_name(f"demo_{device}.json")
    last = [ln for ln in proc.stdout.splitlines() if "done," in ln]
    out = {
        "command": " ".join(["atgs-train --out runs/demo", *args.train_args, *extra]),
        "printed": last[-1] if last else "",
        "psnr": res["eval"]["psnr"], "ssim": res["eval"]["ssim"], "eval_views": res["eval"]["views"],
        "steps": res["steps"], "train_seconds": res["seconds"], "wall_seconds": wall,
        "fresh_cache": not args.reuse_cache, "device": device,
        "budget_seconds": res.get("budget_seconds"), "seconds_per_step": res.get("seconds_per_step"),
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "loadavg_before": list(load_before), "loadavg_after": list(os.getloadavg())},
        "commit": git_commit(ROOT), "date": time.strftime("%Y-%m-%d"),
    }
    scenes = sorted((Path(env.get("ATGS_CACHE_DIR", Path.home() / ".cache" / "atgs"))).glob("synth-*/prepared-v*"))
    if scenes and not extra and not args.train_args:  # the built-in scene the run trained on
        out["split"] = held_out_splits(run / "ckpt.pt", scenes[-1])
    if args.what:
        out["what"] = args.what
    if args.out.exists():  # the run this one replaces goes to previous_runs
        old = json.loads(args.out.read_text())
        sp = old.get("split") or {}
        out["previous_runs"] = [*old.get("previous_runs", []), {
            "what": old.get("what", f"commit {old.get('commit', '?')}"), "psnr": round(old["psnr"], 2),
            "ssim": round(old["ssim"], 3), "steps": old["steps"], "date": old.get("date"),
            **{k: sp[k] for k in ("psnr_moving", "psnr_static", "psnr_seen", "psnr_unseen") if k in sp}}]
    write_json_atomic(args.out, out, indent=2)
    print(f"wrote {args.out}: held-out PSNR {out['psnr']:.2f} dB, SSIM {out['ssim']:.4f}, "
          f"{out['steps']} steps, {wall / 60:.1f} min wall")


if __name__ == "__main__":
    main()
