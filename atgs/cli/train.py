"""``atgs-train``: train ATGS on a prepared scene (or the built-in synthetic scene).

    atgs-train --data DIR --out DIR [--preset cpu-fast|cpu|cpu-accurate|paper] [--iterations N] [--resume]

Every model/trainer knob is a flag (``--model.*``, ``--train.*``; see ``atgs-train --help``);
flag defaults come from the chosen preset.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import json
import os
from pathlib import Path
import sys
from typing import Literal

import tyro

from atgs.model.config import ModelConfig, TrainConfig, preset, to_dict

PresetName = Literal["cpu-fast", "cpu", "cpu-accurate", "paper", "tiny"]


def default_cache_dir() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "atgs"


@dataclass
class TrainArgs:
    out: Path = Path("runs/atgs")
    """Output directory: ckpt.pt, train_log.csv, config.json, renders/."""
    data: Path | None = None
    """Prepared scene directory (atgs-prepare); default: the built-in synthetic scene."""
    preset: PresetName = "cpu"
    """Configuration preset (fast -> accurate: cpu-fast, cpu, cpu-accurate; paper = GPU sizes)."""
    iterations: int | None = None
    """Training steps (rescales the preset's schedule); with --resume: the new total."""
    resume: bool = False
    """Continue the run in --out from its ckpt.pt (configuration from the checkpoint)."""
    overwrite: bool = False
    """Start a new run even if --out already holds a checkpoint (it is replaced at the first save)."""
    progress: bool = True
    cache_dir: Path = field(default_factory=default_cache_dir)
    """Where the built-in synthetic scene is cached."""
    synth_keyframes: int = 6
    """Keyframes of the built-in synthetic scene (when --data is not given)."""
    auto: bool = False
    """Measure the scene's motion and choose K, M, hash table size and spatial grid resolution
    from it (printed with the reasons); --model.* flags given explicitly still win."""
    model: ModelConfig = field(default_factory=ModelConfig)
    train: TrainConfig = field(default_factory=TrainConfig)


def _scan(argv: list[str], flag: str) -> str | None:
    """Value of ``--flag X`` / ``--flag=X`` (read before tyro so that presets set defaults)."""
    for i, a in enumerate(argv):
        if a == flag and i + 1 < len(argv):
            return argv[i + 1]
        if a.startswith(flag + "="):
            return a.split("=", 1)[1]
    return None


def parse(argv: list[str]) -> TrainArgs:
    name = _scan(argv, "--preset") or "cpu"
    it = _scan(argv, "--iterations")
    try:
        m, t = preset(name, int(it) if it is not None and it.lstrip("-").isdigit() else None)
    except ValueError:
        m, t = preset("cpu")  # tyro reports the bad value below
    return tyro.cli(TrainArgs, default=TrainArgs(preset=name if name in PresetName.__args__ else "cpu",
                                                 model=m, train=t), args=argv)


def load_scene(args: TrainArgs):
    from atgs.data.scene import PreparedScene

    if args.data is None:
        from atgs.data.synth import ensure_default_scene

        print(f"atgs-train: no --data given; using the built-in synthetic scene (cached in {args.cache_dir})")
        path = ensure_default_scene(args.cache_dir, keyframes=args.synth_keyframes, progress=args.progress)
    else:
        path = args.data
    return PreparedScene.load(path)


def explicit_model_flags(argv: list[str]) -> set[str]:
    """Model knobs given on the command line, as dotted field names ("hash.log2_table_size")."""
    names = set()
    for a in argv:
        if a.startswith("--model."):
            names.add(a[len("--model."):].split("=", 1)[0].replace("-", "_"))
    return names


def apply_auto(args: TrainArgs, scene, explicit: set[str]) -> None:
    """--auto: measure the scene and replace the preset's sizes by what the scene needs."""
    from atgs.auto_config import apply_overrides, choose_config, format_choice
    from atgs.data.motion import measure_motion

    stats = measure_motion(scene)
    choice = choose_config(stats, args.model)
    kept = {k: v for k, v in choice.overrides.items() if k not in explicit}
    print("atgs-train: --auto chose (from the measured motion):")
    print(format_choice(choice))
    for k in sorted(set(choice.overrides) - set(kept)):
        print(f"  (--model.{k.replace('_', '-')} given on the command line: kept the given value)")
    args.model = apply_overrides(args.model, kept)


def run(args: TrainArgs, explicit: set[str] = frozenset()) -> dict:
    from atgs.train.trainer import Trainer

    ckpt = args.out / "ckpt.pt"
    if args.resume:
        if not ckpt.is_file():
            raise SystemExit(f"atgs-train: --resume: {ckpt} not found; start without --resume")
        scene = load_scene(args)
        trainer = Trainer.resume(scene, ckpt, args.out, iterations=args.iterations)
        print(f"atgs-train: resuming at step {trainer.step} of {trainer.cfg.iterations}")
    else:
        if ckpt.exists() and not args.overwrite:
            raise SystemExit(f"atgs-train: {ckpt} already exists; pass --resume to continue it, "
                             "--overwrite to start over, or choose another --out")
        if args.iterations is not None:
            args.train.iterations = args.iterations
        scene = load_scene(args)
        if args.auto:
            apply_auto(args, scene, explicit)
        trainer = Trainer(scene, args.model, args.train, args.out)
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "config.json").write_text(json.dumps(
            {"preset": args.preset, "data": str(args.data) if args.data else None,
             "model": to_dict(args.model), "train": to_dict(args.train)}, indent=1))
        print(f"atgs-train: {trainer.model.num_anchors} anchors, {trainer.model.num_keyframes} keyframes, "
              f"{trainer.model.num_segments} temporal grids, {scene.num_frames} frames, "
              f"{len(trainer.train_idx)} training / {len(trainer.test_idx)} test cameras")
    result = trainer.train(progress=args.progress)
    (args.out / "result.json").write_text(json.dumps(result, indent=1))
    ev = result.get("eval", {})
    print(f"atgs-train: done, {result['steps']} steps in {result['seconds']:.0f} s; "
          f"test PSNR {ev.get('psnr', float('nan')):.2f} dB, SSIM {ev.get('ssim', float('nan')):.4f}; "
          f"checkpoint {ckpt}")
    return result


def main(argv: list[str] | None = None) -> None:
    from atgs.checkpoint import CheckpointError

    from atgs.data.errors import DataError

    argv = sys.argv[1:] if argv is None else argv
    args = parse(argv)
    try:
        run(args, explicit_model_flags(argv))
    except (CheckpointError, DataError) as e:
        print(f"atgs-train: error: {e}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
