"""Knobs of short CPU runs, measured: the `cpu` preset on a short budget, one change at a time.

    python bench/short_runs.py --cases base grow-4e-4                 # the built-in scene
    python bench/short_runs.py --scene DIR --label stereo --cases base  # another prepared scene

Each case trains preset `cpu` with a time budget (`--minutes`, default 8) on one torch thread
(the runs of the table went two at a time side by side on the 2-core machine, so each had one
core) and reports atgs-train's final held-out evaluation (every frame of the test cameras).
Cases change one thing against `base` (the preset as it was before this bench: growth threshold
2e-4, the paper's learning rates); "extension" in the label means the scene's keyframe points
include the surface extension of atgs-prepare (PREPARE_VERSION 3), "stereo" means they do not
(PREPARE_VERSION 2). Results: bench/results/short_runs.json (merged by label and case) and the
bench:short-runs table in docs/training.md.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import tyro
from _docs import publish, run_stamp  # bench/ (the script's own folder is on sys.path)
from _harness import build_trainer, case_configs, run_timed

from atgs.data.scene import PreparedScene
from atgs.data.synth.videos import ensure_default_scene
from atgs.io.cache import cache_dir

ROOT = Path(__file__).resolve().parent.parent
LR5 = ("anchor_feature", "spatial_grid", "offset_init", "color_init", "opacity_init")
CASES: dict[str, dict] = {  # name: overrides of TrainConfig ("densify.x", "lr.x", or a field)
    "base": {"densify.grad_threshold": 2e-4},
    "grow-1e-4": {"densify.grad_threshold": 1e-4},
    "grow-4e-4": {"densify.grad_threshold": 4e-4},
    "no-growth": {"densify.enabled": False},
    "3-cameras-per-frame": {"densify.grad_threshold": 2e-4, "cameras_per_frame": 3},
    "grow-4e-4, lr x2": {"densify.grad_threshold": 4e-4, **{f"lr.{k}": 2.0 for k in LR5}},
    "grow-4e-4, lr x0.5": {"densify.grad_threshold": 4e-4, **{f"lr.{k}": 0.5 for k in LR5}},
    "grow-4e-4, f_a and F_s lr x0.5": {"densify.grad_threshold": 4e-4, "lr.anchor_feature": 0.5,
                                        "lr.spatial_grid": 0.5},
}
# "lr.*" values are factors of the preset's rate; everything else is set as given.


@dataclass
class ShortRuns:
    cases: tuple[str, ...] = tuple(CASES)
    scene: Path | None = None
    """A prepared scene; default: the built-in large-motion scene (cached)."""
    label: str = "built-in, stereo + extension"
    minutes: float = 8.0
    threads: int = 1
    cache: Path = field(default_factory=cache_dir)
    work_dir: Path = Path("/tmp/atgs-bench-short")
    out: Path = ROOT / "bench" / "results" / "short_runs.json"
    docs: Path = ROOT / "docs" / "training.md"


def train_overrides(name: str, minutes: float) -> dict:
    """The case's overrides with its learning-rate factors turned into rates (the preset's x factor)."""
    _, preset_train = case_configs("cpu", minutes=minutes)
    out = {}
    for key, value in CASES[name].items():
        if key.startswith("lr."):
            value *= getattr(preset_train.lr, key.split(".", 1)[1])
        out[key] = value
    return out


def run_case(scene, name: str, args: ShortRuns) -> dict:
    out = args.work_dir / name.replace(" ", "_").replace(",", "")
    tr = build_trainer(scene, out, "cpu", minutes=args.minutes, train=train_overrides(name, args.minutes),
                       threads=args.threads)
    timed = run_timed(tr, "renders")
    ev = timed.eval
    return {"case": name, "label": args.label, "overrides": CASES[name], "minutes": args.minutes,
            "threads": args.threads, "steps": tr.step, "train_s": round(timed.seconds, 1),
            "anchors": tr.model.num_anchors, "psnr": ev["psnr"], "ssim": ev["ssim"], "views": ev["views"],
            **run_stamp()}


def table(rows: list[dict]) -> str:
    lines = ["| scene points | case | steps | anchors at the end | held-out PSNR | SSIM |", "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['label']} | {r['case']} | {r['steps']:,} | {r['anchors']:,} | {r['psnr']:.2f} | "
                     f"{r['ssim']:.3f} |")
    lines.append("")
    lines.append(f"Preset cpu, {rows[0]['minutes']:g}-minute budget, {rows[0]['threads']} torch thread, two runs side "
                 "by side on 2 cores (load ~2); built-in large-motion scene, cam00 held out, all 120 frames; one "
                 "seed each (differences under ~0.3 dB are within run-to-run noise).")
    return "\n".join(lines)


def main() -> None:
    args = tyro.cli(ShortRuns)
    path = args.scene or ensure_default_scene(args.cache, keyframes=6, progress=True)
    scene = PreparedScene.load(path)
    old = json.loads(args.out.read_text())["rows"] if args.out.exists() else []
    for name in args.cases:
        row = run_case(scene, name, args)
        print(json.dumps(row), flush=True)
        old = [r for r in old if (r["label"], r["case"]) != (row["label"], row["case"])] + [row]
        publish({"rows": old}, args.out, table(old), args.docs, "short-runs")


if __name__ == "__main__":
    main()
