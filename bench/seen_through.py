"""How much opacity a trained model leaves in space its training cameras see through.

    python bench/seen_through.py --runs RUN_DIR [RUN_DIR ...] --names off on
    python bench/seen_through.py --replot

For each run (a folder with ckpt.pt, trained on a prepared scene), every training camera is
rendered at every measured frame (the keyframes and motion keyframes) with only the Gaussians
that stand in front of the depth that camera measured along the ray through their centre, and
the opacity they accumulate on pixels whose measured depth lies behind them is averaged over the
image: exactly the per-ray free-space term of training (atgs.train.losses.ray_free_space_loss,
atgs/geometry/ray_free_space.py), read from a finished model, whether or not it trained with the
term. 0 means no training ray's measured depth is contradicted by fog in front of it.

Held-out cameras are not used: the measured depths are the training cameras' own. Results:
bench/results/seen_through.json (merged by name) and the bench:seen_through table in
docs/training.md.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import tyro

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _docs import publish, run_stamp  # noqa: E402

RESULTS = ROOT / "bench" / "results" / "seen_through.json"


@dataclass
class SeenThroughBench:
    runs: tuple[Path, ...] = ()
    """Run folders (each with ckpt.pt) trained on the same or different prepared scenes."""
    names: tuple[str, ...] = ()
    """A name per run (default: the folder's name)."""
    data: Path | None = None
    """The prepared scene (default: the one each checkpoint recorded)."""
    out: Path = RESULTS
    docs: Path | None = ROOT / "docs" / "training.md"
    replot: bool = False  # the table again from the results file, nothing measured


def seen_through(run: Path, data: Path | None) -> dict:
    from atgs.checkpoint import model_from_checkpoint, read_checkpoint
    from atgs.cli.evaluate import checkpoint_data_dir
    from atgs.data.scene import PreparedScene
    from atgs.train.losses import per_keyframe_gaussians, ray_free_space_loss
    from atgs.train.scene_setup import measured_depths_of

    ckpt = read_checkpoint(run / "ckpt.pt")
    model = model_from_checkpoint(ckpt, run / "ckpt.pt")
    data = data or checkpoint_data_dir(ckpt)
    if data is None:
        raise SystemExit(f"{run}/ckpt.pt records no prepared scene; give --data")
    scene = PreparedScene.load(data)
    train = scene.train_indices
    cams = [scene.cameras[i] for i in train]
    t0 = time.perf_counter()
    measured = measured_depths_of(scene, cams, lambda s, f: scene.image_uint8(train[s], f), "cpu")
    if measured is None:
        raise SystemExit(f"{run}: the scene has no measured points")
    per_camera: dict[str, list[float]] = {c.name: [] for c in cams}
    frames = sorted(measured.at_frame)
    with torch.no_grad():
        for f in frames:
            dec = model.decode_frame(f, track=False)
            moving = per_keyframe_gaussians(model.anchor_keyframe, dec.anchor_ids)
            for slot, cam in enumerate(cams):
                v = ray_free_space_loss(dec.gaussians, moving, measured, slot, f, cam, near=model.near)
                per_camera[cam.name].append(0.0 if v is None else float(v))
    cam_mean = {n: sum(v) / len(v) for n, v in per_camera.items()}
    worst = max(cam_mean, key=cam_mean.get)
    result = json.loads((run / "result.json").read_text())
    return {"run": str(run), "steps": result.get("steps"), "held_out_psnr": round(result["eval"]["psnr"], 2),
            "measured_frames": len(frames), "training_cameras": len(cams),
            "alpha_in_front": round(sum(cam_mean.values()) / len(cam_mean), 5),
            "worst_camera": worst, "worst_alpha_in_front": round(cam_mean[worst], 5),
            "per_camera": {n: round(v, 5) for n, v in cam_mean.items()}, "seconds": round(time.perf_counter() - t0, 1),
            **run_stamp()}


def table(rows: dict[str, dict]) -> str:
    out = ["| run | steps | held out PSNR | training cameras x measured frames | opacity in front of the "
           "measured depth (mean) | worst training camera |", "|---|---|---|---|---|---|"]
    for name, r in rows.items():
        out.append(f"| {name} | {r['steps']} | {r['held_out_psnr']:.2f} dB | {r['training_cameras']} x "
                   f"{r['measured_frames']} | {r['alpha_in_front']:.4f} | {r['worst_camera']}: "
                   f"{r['worst_alpha_in_front']:.4f} |")
    return "\n".join(out)


def main() -> None:
    cfg = tyro.cli(SeenThroughBench, description=__doc__)
    names = list(cfg.names) or [r.name for r in cfg.runs]
    if len(names) != len(cfg.runs):
        raise SystemExit("--names: give one name per run")
    rows = json.loads(cfg.out.read_text())["rows"] if cfg.out.is_file() else {}
    if not cfg.replot:
        for name, run in zip(names, cfg.runs):
            res = rows[name] = seen_through(run, cfg.data)
            print(f"{name}: mean opacity in front of the measured depth {res['alpha_in_front']:.4f} over "
                  f"{res['training_cameras']} training cameras x {res['measured_frames']} measured frames "
                  f"(worst camera {res['worst_camera']}: {res['worst_alpha_in_front']:.4f}; {res['seconds']} s)",
                  flush=True)
    publish({"rows": rows}, cfg.out, table(rows), cfg.docs, "seen_through")


if __name__ == "__main__":
    main()
