"""The README's headline table: how good the results are and how fast training, the player and
the tests run, in at most eight rows, each read from one results file. Every figure comes from a
JSON field; the targets and verdicts stay with the full table (docs/benchmarks.md,
bench/_full_table.py). Written and checked by bench/readme_table.py."""

from __future__ import annotations

from pathlib import Path

from _full_table import STAGE_CAMERAS, demo_figure, real_rigs, rig_cameras
from _table import Cells, Row, count, markdown_row, span

PAGE = Path(__file__).resolve().parent.parent / "README.md"
NAME = "readme"  # its bench:readme markers
HEAD = "| | measured | how |\n|---|---|---|"
MAX_ROWS = 8  # a first screen, not a report


def day(date: str | None) -> str:
    return date[:10] if date else "date not recorded"


def cores(n: int) -> str:
    return f"{n} CPU cores"


def real_capture(r: dict) -> Cells:
    s = r["cases"]["stereo"]
    seeds = len(r.get("seeds", [0]))
    return Cells(f"preset `{r['preset']}`, {r['minutes']:g} min on {cores(r['cpus'])}, "
                 + (f"mean of {seeds} seeds, " if seeds > 1 else "")
                 + f"{r['test_camera']} held out, images at 1/{r['downscale']} size", day(r["date"]),
                 f"{s['psnr']:.2f} dB PSNR, SSIM {s['ssim']:.3f}")


def built_in_scene(r: dict) -> Cells:
    demo_figure(r)  # the stored figures are those atgs-train printed
    return Cells(f"`{r['command']}` as `./scripts/demo.sh` runs it: its {r['budget_seconds'] / 60:g}-minute "
                 f"budget on {cores(r['machine']['cpus'])}, {r['eval_views']} held-out views",
                 day(r["date"]), f"{r['psnr']:.2f} dB PSNR, SSIM {r['ssim']:.3f}")


def capture_rigs(r: dict) -> Cells:
    rows = {x["case"]: x for x in r["rows"]}
    dome, ring = rows["dome24"], rows["ring10-loose"]
    real = real_rigs(rows)
    domes = [x for x in real if rig_cameras(x) >= STAGE_CAMERAS]  # the rest are sparse rigs
    sparse = [x for x in real if x not in domes]
    sizes = dict.fromkeys(rig_cameras(x) for x in domes)  # one dome may be run at several resolutions
    real_domes = "".join(f", real {n}-camera dome" for n in sizes)
    dome_figures = "".join(f"; real {n}-camera dome " + ", ".join(
        f"{x['psnr']:.2f} dB at {x['cameras'].split(', ')[1]}" for x in domes if rig_cameras(x) == n) for n in sizes)
    return Cells(f"synthetic {rig_cameras(dome)}-camera dome, {rig_cameras(ring)}-camera ring with near/far 10x "
                 f"too wide"
                 f"{real_domes}, real rigs of {span([rig_cameras(x) for x in sparse], '{:.0f}')} cameras; preset "
                 f"`{dome['preset']}`, {dome['minutes']:g} min each on "
                 f"{dome['machine'].split(', ')[-1].replace('cores', 'CPU cores')}",
                 day(min(x["date"] for x in rows.values())),
                 f"dome {dome['psnr']:.2f} dB, ring {ring['psnr']:.2f} dB{dome_figures}; real sparse rigs "
                 f"{span([x['psnr'] for x in sparse], '{:.2f}')} dB")


def cpu_training(r: dict) -> Cells:
    return Cells(f"the built-in scene's run above, preset `cpu` (`--train.minutes` sets another budget), "
                 f"{cores(r['machine']['cpus'])}", day(r["date"]),
                 f"{r['budget_seconds'] / 60:g}-minute budget: {r['steps']:,} steps at "
                 f"{r['train_seconds'] / r['steps']:.2f} s")


def gpu_training(r: dict) -> Cells:
    rows = [x for x in r["rows"] if x["part"] == "train" and x["device"] == "cuda" and "status" not in x]
    if not rows:
        return Cells("no CUDA device seen by the last run", day(r.get("date")), "not measured on a GPU")
    names = ", ".join(sorted({x["device_name"] for x in rows}))
    return Cells(f"every preset, {rows[0]['cameras']} cameras at {rows[0]['size']} (an N3DV-like scene), on an {names}",
                 day(r["parts"]["train/cuda"]["date"]),
                 f"{span([x['ms_per_step'] / 1000 for x in rows], '{:.2f}')} s a step "
                 f"({span([x['steps_per_s'] for x in rows])} steps/s)")


def cpu_player(r: dict) -> Cells:
    played = [x for x in r["playback"] if x["min_alpha_255"] == 1]
    adaptive = [x for x in played if x["adaptive"]]
    # the same playbacks without the adaptive resolution: "scene (mode)" of "scene (mode, adaptive resolution)"
    same = {x["scene"].replace(", adaptive resolution)", ")") for x in adaptive}
    full = [x for x in played if not x["adaptive"] and x["scene"] in same]
    gl = r["machine"]["gl"].split(" (")[0]
    return Cells(f"{adaptive[0]['size']}, the built-in scene and a trained model "
                 f"({count(min(x['gaussians'] for x in played))}-{count(max(x['gaussians'] for x in played))} "
                 f"Gaussians), software OpenGL ({gl}) on {cores(r['machine']['cpus'])}; the adaptive resolution drew "
                 f"the splats at {span([x['mean_scale'] for x in adaptive], '{:.2f}')} of the window's size",
                 day(r["date"]), f"{span([x['fps'] for x in adaptive])} FPS with the player's adaptive resolution, "
                 f"{span([x['fps'] for x in full])} FPS at full resolution")


def gpu_player(r: dict) -> Cells:
    rows = [x for x in r["rows"] if x["part"] == "content" and x["device"] == "cuda" and "status" not in x]
    if not rows:
        return Cells("no CUDA device seen by the last run", day(r.get("date")), "not measured on a GPU")
    x = rows[0]
    return Cells(f"the built-in scene's trained model, {count(x['gaussians'])} Gaussians, at {x['size']} on an "
                 f"{x['device_name']}", day(r["parts"]["content/cuda"]["date"]),
                 f"{x['fps_new_frame']:.0f} FPS playing, {x['fps_camera_move']:.0f} FPS moving the camera")


def test_suite(r: dict) -> Cells:
    subset = f"only `{' '.join(r['pytest_args'])}` of " if r["pytest_args"] else ""
    return Cells(f"{subset}`./scripts/test.sh`'s pytest on {cores(r['machine']['cpus'])}", day(r["date"]),
                 f"{r['passed']} passed, {r['skipped']} skipped, {r['failed'] + r['errors']} failed in "
                 f"{r['seconds'] / 60:.1f} min")


ROWS = (
    Row("n3dv", "n3dv.py", "Quality, real capture: one frame of an N3DV video, a held-out camera", "", real_capture),
    Row("demo", "demo.py", "Quality, the built-in synthetic scene: moving objects, a held-out camera",
        "", built_in_scene),
    Row("rigs", "rigs.py", "Quality, capture rigs: held-out cameras", "", capture_rigs),
    Row("demo", "demo.py", "Training time, CPU", "", cpu_training),
    Row("gpu", "gpu.py", "Training speed, GPU", "", gpu_training),
    Row("viewer", "viewer.py", "Player, CPU: playing the video", "", cpu_player),
    Row("gpu", "gpu.py", "Player, GPU", "", gpu_player),
    Row("test_suite", "test_suite.py", "Test suite", "", test_suite),
)


def line(row: Row, c: Cells | None) -> str:
    """| label | measured | how it was measured (script, day) |"""
    script = f"`bench/{row.script}`"
    if c is None:
        return markdown_row((row.label, f"not measured (run {script})", ""))
    return markdown_row((row.label, c.measured, f"{c.details} ({script}, {c.run})"))
