"""``atgs-eval CKPT [--data DIR] [--out DIR] ...``: score a checkpoint on held-out cameras.

Writes per_view.csv, summary.json and render|GT|error images (see :mod:`atgs.eval.evaluate`)
and prints the mean metrics. Bad input gives one line on stderr and exit code 2 (atgs.io.cli).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import tyro

from atgs.eval.evaluate import METRICS, EvalConfig, EvalError, EvalResult, evaluate
from atgs.io.cli import run_cli


@dataclass
class EvalArgs:
    """Evaluate an ATGS checkpoint on the test cameras of a prepared scene."""

    ckpt: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="CKPT")]
    """Checkpoint file written by atgs-train (ckpt.pt)."""
    data: Path | None = None
    """Prepared scene directory (default: the data path stored in the checkpoint)."""
    out: Path | None = None
    """Output directory (default: an 'eval' directory beside the checkpoint); replaced only on success."""
    eval: Annotated[EvalConfig, tyro.conf.OmitArgPrefixes] = field(default_factory=EvalConfig)


def checkpoint_data_dir(ckpt: dict[str, Any]) -> Path | None:
    """The prepared-scene path the model was trained on, if the checkpoint recorded one (the
    trainer stores it as "data_dir"; "" when it trained on an in-memory scene)."""
    v = ckpt.get("data_dir")
    return Path(v) if isinstance(v, str) and v else None


def run(args: EvalArgs) -> EvalResult:
    """Load checkpoint and scene, evaluate, write outputs (raises EvalError, DataError or
    CheckpointError with one-line messages on bad input)."""
    from atgs.checkpoint import model_from_checkpoint, read_checkpoint
    from atgs.data.scene import PreparedScene

    if not args.ckpt.is_file():
        raise EvalError(f"{args.ckpt}: checkpoint not found; pass the ckpt.pt written by atgs-train")
    ckpt = read_checkpoint(args.ckpt)  # validated, weights_only: the same path as atgs.load()
    model = model_from_checkpoint(ckpt, args.ckpt)
    data = args.data or checkpoint_data_dir(ckpt)
    if data is None:
        raise EvalError(f"{args.ckpt} does not record its data directory; pass --data DIR")
    if not Path(data).is_dir():
        raise EvalError(f"--data {data}: not a directory" + ("" if args.data else " (path stored in the checkpoint)"))
    scene = PreparedScene.load(data)
    out = args.out or args.ckpt.parent / "eval"
    settings = {"checkpoint": str(args.ckpt.resolve()), "data": str(Path(data).resolve()),
                "step": ckpt.get("step")}
    # over what training used: model_from_checkpoint gave the model its environment map or colour
    return evaluate(model, scene, args.eval, out, settings=settings)


def format_summary(result: EvalResult) -> str:
    def f(v: Any) -> str:
        return v if isinstance(v, str) else f"{v:.4f}"

    lines = [f"{result.summary['num_views']} views -> {result.out_dir}"]
    lines.append("  mean      " + "  ".join(f"{m}={f(result.mean(m))}" for m in METRICS))
    for cam, means in result.summary["per_camera"].items():
        lines.append(f"  {cam:<9} " + "  ".join(f"{m}={f(means[m])}" for m in METRICS))
    if not result.summary["lpips"]["available"]:
        lines.append(f"  lpips unavailable: {result.summary['lpips']['reason']}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = tyro.cli(EvalArgs, args=argv)
    return run_cli("atgs-eval", lambda: print(format_summary(run(args))), process=argv is None)


if __name__ == "__main__":
    sys.exit(main())
