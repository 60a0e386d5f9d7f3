"""Speed versus accuracy: every preset, --auto, the anchor layouts and one-knob sweeps, trained on
both built-in scenes (small-motion and large-motion).

    python bench/tradeoff.py                          # everything (about 1.5 h on 2 cores)
    python bench/tradeoff.py --only presets auto      # a subset of the groups
    python bench/tradeoff.py --scenes large-motion --iterations 400

Per run: held-out PSNR / SSIM, training time, viewer decode time (``gaussians_at_frame``) and
draw time (headless GLSL splatting at 640x480 incl. sort and upload), model size (checkpoint
without optimizer state), anchors, Gaussians per frame and peak memory. Each run is its own
subprocess (its own peak RSS); ``--jobs 2`` runs two at once with one torch thread each, which
is how the timings are meant (2-core machine). Results: bench/results/tradeoff.json (merged by
run name, so a partial rerun keeps the rest), the table in docs/tradeoff.md and the plot
docs/images/tradeoff.png.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, replace
import io
import json
import os
import shutil
from pathlib import Path
import sys
import time

import tyro

from _docs import publish, write_json_atomic  # bench/_docs.py (the script's own folder is on sys.path)

from atgs.io.atomic import atomic_file
from atgs.io.cache import cache_dir

ROOT = Path(__file__).resolve().parent.parent

GROUPS = ("presets", "auto", "layout", "sweep", "layout-full")


@dataclass
class TradeoffArgs:
    scenes: tuple[str, ...] = ("small-motion", "large-motion")
    only: tuple[str, ...] = GROUPS
    names: tuple[str, ...] = ()  # run only these run names (e.g. "q=10")
    frames: int = 48
    cameras: int = 16  # a dense ring: with 10 cameras held-out views are 36 degrees from any training view
    width: int = 128
    height: int = 96
    keyframes: int = 12  # keyframes of the prepared scene; runs use K=6 of them unless swept
    test_cameras: int = 2
    iterations: int = 800  # sweeps, layouts and --auto: cpu-fast with its schedule compressed to this
    # (the base of the sweeps is the "preset cpu-fast" run: the same configuration)
    preset_fraction: float = 0.4  # presets train this fraction of their default iterations ...
    preset_max_iterations: int = 800  # ... capped here: an equal step budget (2 cores)
    jobs: int = 2
    threads: int = 1  # torch threads per run
    draw_size: tuple[int, int] = (640, 480)
    cache_dir: Path = field(default_factory=cache_dir)  # $ATGS_CACHE_DIR, else ~/.cache/atgs
    work_dir: Path = Path("/tmp/atgs-bench-tradeoff")
    out: Path = ROOT / "bench" / "results" / "tradeoff.json"
    docs: Path = ROOT / "docs" / "tradeoff.md"
    plot: Path = ROOT / "docs" / "images" / "tradeoff.png"
    replot: bool = False  # only redraw table and plot from the results file
    rerun: bool = False  # run again runs whose results are already in the results file


@dataclass
class RunSpec:
    name: str
    group: str
    scene: str
    preset: str
    iterations: int
    model_overrides: dict = field(default_factory=dict)
    train_overrides: dict = field(default_factory=dict)
    auto: bool = False
    frames: int = 48
    cameras: int = 16
    width: int = 128
    height: int = 96
    keyframes: int = 12
    test_cameras: int = 2
    threads: int = 1
    draw_size: tuple[int, int] = (640, 480)


# One-knob sweeps around the base (cpu-fast, K=6): (run name, model overrides, train overrides).
SWEEPS: list[tuple[str, dict, dict]] = [
    ("q=2", {"gaussians_per_anchor": 2}, {}),
    ("q=10", {"gaussians_per_anchor": 10}, {}),
    ("K=3", {"num_keyframes": 3}, {}),
    ("K=12", {"num_keyframes": 12}, {}),
    ("M=1", {"num_segments": 1}, {}),
    ("M=4", {"num_segments": 4}, {}),
    ("features=16", {"feature_dim": 16}, {}),
    ("features=64", {"feature_dim": 64}, {}),
    ("hash=2^12", {"hash.log2_table_size": 12}, {}),
    ("hash=2^16", {"hash.log2_table_size": 16}, {}),
    ("grid res=16", {"spatial_resolution": 16}, {}),
    ("grid res=64", {"spatial_resolution": 64}, {}),
    ("images x0.5", {}, {"resolution_scale": 0.5}),
]
BASE_MODEL = {"num_keyframes": 6}


def plan(args: TradeoffArgs) -> list[RunSpec]:
    from atgs.train.config import preset

    common = dict(frames=args.frames, cameras=args.cameras, width=args.width, height=args.height,
                  keyframes=args.keyframes, test_cameras=args.test_cameras, threads=args.threads,
                  draw_size=tuple(args.draw_size))
    specs: list[RunSpec] = []
    for scene in args.scenes:
        def add(name: str, group: str, p: str, it: int, mo: dict | None = None, to: dict | None = None,
                auto: bool = False) -> None:
            specs.append(RunSpec(name, group, scene, p, it, {**BASE_MODEL, **(mo or {})}, to or {}, auto, **common))

        if "presets" in args.only:
            for p in ("cpu-fast", "cpu", "cpu-accurate", "paper"):
                it = min(args.preset_max_iterations, max(50, round(preset(p)[1].iterations * args.preset_fraction)))
                add(f"preset {p}", "presets", p, it)
        if "auto" in args.only:
            add("cpu-fast --auto", "auto", "cpu-fast", args.iterations, auto=True)
        if "layout" in args.only:
            add("per-keyframe anchors (paper)", "layout", "cpu-fast", args.iterations,
                {"anchor_layout": "per-keyframe"}, {"densify.final_prune": False})
            add("split, no final prune", "layout", "cpu-fast", args.iterations, {}, {"densify.final_prune": False})
        if "layout-full" in args.only:  # the layouts again at cpu-fast's own full schedule
            it = preset("cpu-fast")[1].iterations
            add(f"{it} steps, split", "layout-full", "cpu-fast", it)
            add(f"{it} steps, per-keyframe", "layout-full", "cpu-fast", it, {"anchor_layout": "per-keyframe"})
        if "sweep" in args.only:
            for name, mo, to in SWEEPS:
                add(name, "sweep", "cpu-fast", args.iterations, mo, to)
    if args.names:
        specs = [s for s in specs if s.name in args.names]
    return sorted(specs, key=lambda s: GROUPS.index(s.group))  # the main comparisons first


def load_scene(spec: RunSpec, cache_dir: Path):
    from _harness import ring_scene

    return ring_scene(cache_dir, keyframes=spec.keyframes, test_cameras=spec.test_cameras, preset=spec.scene,
                      frames=spec.frames, cameras=spec.cameras, width=spec.width, height=spec.height)


def viewer_times(model, camera, size: tuple[int, int], frames: list[int]) -> dict:
    """Mean decode ms (inference path, sequential frames after a warm-up) and mean draw ms
    (pack + upload + sort + GLSL splatting at ``size``, finished) of the headless viewer."""
    import numpy as np

    model.gaussians_at_frame(frames[0])  # warm the time-invariant caches
    dec = []
    gs = []
    for f in frames:
        t0 = time.perf_counter()
        g = model.gaussians_at_frame(f)
        dec.append(time.perf_counter() - t0)
        gs.append(g)
    out = {"decode_ms": 1000 * float(np.mean(dec)), "gaussians_per_frame": float(np.mean([len(g) for g in gs]))}
    try:
        from atgs.viewer.headless import HeadlessRenderer
        from atgs.viewer.packing import pack_gaussians
        from atgs.viewer.splat_renderer import RenderSettings

        hr = HeadlessRenderer(model)
        cam = camera.scaled(size[0] / camera.width)
        settings = RenderSettings()
        hr.set_frame(pack_gaussians(gs[0], frames[0]))
        hr.renderer.render(cam, settings)  # compile shaders, allocate targets
        draw = []
        for f, g in zip(frames, gs):
            t0 = time.perf_counter()
            hr.set_frame(pack_gaussians(g, f))
            hr.renderer.render(cam, settings, sync=True)
            draw.append(time.perf_counter() - t0)
        hr.close()
        out["draw_ms"] = 1000 * float(np.mean(draw))
        out["gl"] = "ok"
    except Exception as e:  # no OpenGL: the rest of the row still counts
        out["draw_ms"], out["gl"] = None, f"{type(e).__name__}: {e}"
    return out


def run_one(spec: RunSpec, cache_dir: Path, work_dir: Path) -> dict:
    import resource

    import torch
    from _harness import build_trainer, case_configs, run_timed

    from atgs.timeline import evenly_spaced

    torch.set_num_threads(spec.threads)
    scene = load_scene(spec, cache_dir)
    chosen = {}
    if spec.auto:  # --auto: the scene's measured motion picks K, M, table size and grid over the case's model
        from atgs.auto_config import choose_config
        from atgs.data.motion_measure import measure_motion

        m, _ = case_configs(spec.preset, iterations=spec.iterations, model=spec.model_overrides)
        chosen = dict(choose_config(measure_motion(scene), m).overrides)
    out = work_dir / spec.scene / spec.name.replace(" ", "_").replace("/", "_")
    trainer = build_trainer(scene, out, spec.preset, iterations=spec.iterations,
                            model={**spec.model_overrides, **chosen}, train=spec.train_overrides, threads=spec.threads)
    res = run_timed(trainer, "none").result
    ev = trainer.evaluate(resolution_scale=1.0)  # full resolution whatever the training resolution
    model = trainer.model
    payload = trainer.checkpoint_payload()
    payload["trainer"] = None
    buf = io.BytesIO()
    torch.save(payload, buf)
    frames = evenly_spaced(model.num_frames, 8)
    vt = viewer_times(model, scene.cameras[scene.test_indices[0]], tuple(spec.draw_size), frames)
    peak_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    static = int((model.anchor_keyframe < 0).sum())
    ckpt_mb = (out / "ckpt.pt").stat().st_size / 2**20
    shutil.rmtree(out)  # GPU-sized presets write GBs of checkpoints
    return {**asdict(spec), "psnr": ev["psnr"], "ssim": ev["ssim"], "train_seconds": res["seconds"],
            "anchors": model.num_anchors, "static_anchors": static, "final_pruned": res.get("final_pruned", 0),
            "model_mb": len(buf.getvalue()) / 2**20, "ckpt_mb": ckpt_mb,
            "peak_rss_mb": peak_kb / 1024.0, "K": model.num_keyframes, "M": model.num_segments,
            "auto_choice": chosen, **vt}


def run_subprocess(spec: RunSpec, args: TradeoffArgs) -> dict:
    from _harness import last_line, run_child

    cmd = [sys.executable, __file__, "--child", json.dumps(asdict(spec)), str(args.cache_dir), str(args.work_dir)]
    t0 = time.perf_counter()
    r, stderr = run_child(cmd)
    if r is None:
        print(f"[tradeoff] {spec.scene} / {spec.name}: FAILED {last_line(stderr)}", file=sys.stderr, flush=True)
        return {**asdict(spec), "error": last_line(stderr)}
    print(f"[tradeoff] {spec.scene} / {spec.name}: PSNR {r['psnr']:.2f} SSIM {r['ssim']:.3f} "
          f"train {r['train_seconds']:.0f}s decode {r['decode_ms']:.0f}ms draw {r['draw_ms'] or float('nan'):.0f}ms "
          f"model {r['model_mb']:.1f}MB anchors {r['anchors']} ({time.perf_counter() - t0:.0f}s)", flush=True)
    return r


def _key(r: dict) -> str:
    return f"{r['scene']}|{r['name']}"


def table(rows: list[dict]) -> str:
    head = ("| scene | run | it | K | M | anchors (static) | Gaussians/frame | PSNR | SSIM | train s | decode ms | "
            "draw ms | model MB | peak RSS MB |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['scene']} | {r['name']} | failed: {r['error']} |")
            continue
        draw = f"{r['draw_ms']:.0f}" if r.get("draw_ms") is not None else "n/a"
        lines.append(
            f"| {r['scene']} | {r['name']} | {r['iterations']} | {r['K']} | {r['M']} | {r['anchors']} "
            f"({r['static_anchors']}) | {r['gaussians_per_frame']:.0f} | {r['psnr']:.2f} | {r['ssim']:.3f} | "
            f"{r['train_seconds']:.0f} | {r['decode_ms']:.0f} | {draw} | {r['model_mb']:.1f} | "
            f"{r['peak_rss_mb']:.0f} |")
    return "\n".join(lines)


def plot(rows: list[dict], path: Path) -> None:
    """PSNR against training time, viewer decode+draw time and model size, one row per scene."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in rows if "error" not in r and r["group"] != "layout-full"]  # plot: 800-step runs
    scenes = sorted({r["scene"] for r in ok})
    fig, axes = plt.subplots(len(scenes), 3, figsize=(17, 4.4 * len(scenes)), squeeze=False)
    style = {"presets": ("o", "tab:blue"), "auto": ("*", "tab:red"), "layout": ("s", "tab:green"),
             "sweep": (".", "tab:gray")}
    for i, sc in enumerate(scenes):
        for j, (xkey, xlabel) in enumerate((("train_seconds", "training time [s] (800 steps, 1 thread)"),
                                            ("frame_ms", "viewer decode + draw per frame [ms], 640x480"),
                                            ("model_mb", "model size [MB] (checkpoint without optimizer)"))):
            ax = axes[i][j]
            for r in (r for r in ok if r["scene"] == sc):
                x = r["decode_ms"] + (r.get("draw_ms") or 0) if xkey == "frame_ms" else r[xkey]
                mk, col = style[r["group"]]
                ax.scatter(x, r["psnr"], marker=mk, color=col, s=60 if r["group"] != "sweep" else 30)
                ax.annotate(r["name"].replace("preset ", ""), (x, r["psnr"]), fontsize=7,
                            xytext=(3, 3), textcoords="offset points")
            ax.set_xscale("log")
            ax.set_xlabel(xlabel)
            ax.set_ylabel("held-out PSNR [dB]")
            ax.set_title(f"{sc}")
            ax.grid(alpha=0.3)
    handles = [plt.Line2D([], [], marker=m, color=c, linestyle="", label=g) for g, (m, c) in style.items()]
    fig.legend(handles=handles, loc="upper center", ncol=4)
    fig.tight_layout(rect=(0, 0, 1, 0.96))
    with atomic_file(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110)
    print(f"wrote {path}")


def publish_all(results: dict, args: TradeoffArgs) -> None:
    """The results file, the docs table and the plot."""
    order = {g: i for i, g in enumerate(GROUPS)}
    rows = sorted(results["runs"].values(), key=lambda r: (r["scene"], order[r["group"]]))
    publish(results, args.out, table(rows), args.docs, "tradeoff")
    plot(rows, args.plot)


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        spec = RunSpec(**json.loads(sys.argv[2]))
        spec.draw_size = tuple(spec.draw_size)
        print(json.dumps(run_one(spec, Path(sys.argv[3]), Path(sys.argv[4]))))
        return
    args = tyro.cli(TradeoffArgs)
    results = json.loads(args.out.read_text()) if args.out.is_file() else {"runs": {}}
    if args.replot:
        publish_all(results, args)
        return
    specs = plan(args)
    if not args.rerun:  # resume an interrupted benchmark
        specs = [s for s in specs if "error" in results["runs"].get(f"{s.scene}|{s.name}", {"error": 1})]
    # the scenes first, one at a time (synthesis + preparation are cached and not thread safe)
    for sc in args.scenes:
        if specs:
            load_scene(replace(specs[0], scene=sc), args.cache_dir)
    results["machine"] = {"cpus": os.cpu_count(), "jobs": args.jobs, "threads_per_run": args.threads,
                          "loadavg_start": list(os.getloadavg())}
    from tqdm import tqdm

    with ThreadPoolExecutor(args.jobs) as pool, tqdm(total=len(specs), desc="tradeoff runs", unit="run") as bar:
        for r in pool.map(lambda s: run_subprocess(s, args), specs):
            results["runs"][_key(r)] = r
            write_json_atomic(args.out, results)  # keep what finished if interrupted
            bar.update(1)
    results["machine"]["loadavg_end"] = list(os.getloadavg())
    publish_all(results, args)


if __name__ == "__main__":
    main()
