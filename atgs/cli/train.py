"""``atgs-train``: train ATGS on a prepared scene (or the built-in synthetic scene).

    atgs-train [cpu-fast|cpu|cpu-accurate|paper] --data DIR --out DIR [--train.minutes M | --train.iterations N]
               [--resume] [--device auto|cpu|cuda] [--workers N]

Every model/trainer knob is a flag (``--model.*``, ``--train.*``; see ``atgs-train --help``);
their defaults come from the chosen preset, a subcommand (atgs.cli.train_args). Nothing in an existing ``--out`` changes before the new
run's first checkpoint (atgs.train.run_dir); Ctrl-C saves a checkpoint that ``--resume`` continues.

Several workers (atgs.train.distributed): ``torchrun --nproc-per-node N -m atgs.cli.train ...``
with the same flags, or ``atgs-train --workers N``, which runs torchrun's launcher in this process.
Rank 0 prints and writes the run's files; the others print only their errors.
"""

from __future__ import annotations

from dataclasses import replace
import logging
import os
from pathlib import Path
import signal
import sys

from atgs.cli.train_args import PROG, TrainArgs, current_spelling, explicit_model_flags, given_flags, parse
from atgs.config_checks import ConfigError
from atgs.device import auto_fallback_note, device_description, resolve_device
from atgs.errors import OutputError
from atgs.geometry.rig_check import sparse_rig_warning
from atgs.io.cli import EXIT_INTERRUPTED, Interrupted, _exit_now, run_cli, stop_on_sigint
from atgs.train.config import TrainConfig


def load_scene(args: TrainArgs):
    from atgs.data.scene import PreparedScene

    if args.data is None:
        from atgs.data.synth.videos import ensure_default_scene

        print(f"{PROG}: no --data given; using the built-in synthetic scene (cached in {args.cache_dir})", flush=True)
        path = ensure_default_scene(args.cache_dir, keyframes=args.synth_keyframes, progress=args.progress)
    else:
        path = args.data
    return PreparedScene.load(path)


def apply_auto(args: TrainArgs, scene, explicit: set[str]) -> None:
    """--auto: measure the scene and replace the preset's sizes by what the scene needs."""
    from atgs.auto_config import apply_overrides, choose_config, format_choice
    from atgs.data.motion_measure import measure_motion

    stats = measure_motion(scene)
    choice = choose_config(stats, args.model)
    kept = {k: v for k, v in choice.overrides.items() if k not in explicit}
    print(f"{PROG}: --auto chose (from the measured motion):")
    print(format_choice(choice))
    for k in sorted(set(choice.overrides) - set(kept)):
        print(f"  (--model.{k.replace('_', '-')} given on the command line: kept the given value)")
    args.model = apply_overrides(args.model, kept)


def resumed_checkpoint(args: TrainArgs) -> Path:
    """``--out``'s ckpt.pt, which --resume continues."""
    ckpt = args.out / "ckpt.pt"
    if not ckpt.is_file():
        raise OutputError(f"--resume: {ckpt} not found; start without --resume")
    return ckpt


def make_trainer(args: TrainArgs, explicit: set[str] = frozenset(), workers=None):
    """The trainer of a new run (config staged for its first checkpoint) or of a resumed one, on
    this process's place among ``workers`` (atgs.train.distributed.Workers; None: one process).
    Refuses, before any work, to start over a run that --out already holds."""
    from atgs.train.trainer import Trainer

    device = resolve_device(args.device, need_gsplat=True)
    note = auto_fallback_note(args.device, device, need_gsplat=True)
    if note is not None:
        print(f"{PROG}: {note}; see docs/gpu.md", flush=True)
    if workers is not None:
        device = workers.device
    ckpt = args.out / "ckpt.pt"
    if args.resume:
        trainer = Trainer.resume(load_scene(args), resumed_checkpoint(args), args.out, iterations=args.iterations,
                                 minutes=args.minutes, device=device, workers=workers,
                                 partition=args.train.partition if "train.partition" in explicit else None,
                                 time_groups=args.train.time_groups if "train.time_groups" in explicit else None)
        trainer.run.stage_config({"device": str(device)})  # config.json keeps the run's preset and data
        print(f"{PROG}: resuming at step {trainer.step} of {trainer.cfg.iterations} "
              f"on {_where(device, workers, trainer)}")
        return trainer
    if ckpt.exists() and not args.overwrite:
        raise OutputError(f"{ckpt} already exists; pass --resume to continue it, --overwrite to start over, "
                          "or choose another --out")
    scene = load_scene(args)
    if args.auto:
        apply_auto(args, scene, explicit)
    chosen = _views_for_workers(args, explicit, workers)
    trainer = Trainer(scene, args.model, args.train, args.out, device=device, progress=args.progress, workers=workers)
    # config.json: these, and the configuration of each checkpoint (what ran; atgs.train.run_dir)
    trainer.run.stage_config({"preset": args.preset.name, "data": str(args.data) if args.data else None,
                              "device": str(device)})
    m = trainer.model
    print(f"{PROG}: {m.num_anchors} anchors, {m.num_keyframes} keyframes, {m.num_segments} temporal grids, "
          f"{scene.num_frames} frames, {len(trainer.train_idx)} training / {len(trainer.test_idx)} test cameras, "
          f"on {_where(device, workers, trainer)}{chosen}; "
          + (f"{args.train.minutes:g} min time budget" if args.train.minutes > 0 else f"{args.train.iterations} steps"))
    sparse = sparse_rig_warning([scene.cameras[i] for i in trainer.train_idx],
                                ((getattr(scene, "coverage", None) or {}).get("views_per_pixel") or {}).get("mean"))
    if sparse is not None:  # with the start-up summary (stdout); atgs-prepare said it on stderr
        print(f"{PROG}: {sparse}", flush=True)
    if trainer.measured_exposure is not None:
        g = trainer.measured_exposure.mean(1)
        print(f"{PROG}: camera exposure {trainer.cfg.camera_exposure}: the training cameras' brightness measured "
              f"from the keyframe points spans {g.min():.2f}-{g.max():.2f} of their average (on above "
              f"{trainer.cfg.exposure_threshold:g} in log; --train.camera-exposure on|off to choose)")
    return trainer


def _where(device, workers, trainer) -> str:
    """Where the run trains and how the workers split it, for the start-up line."""
    if workers is None:
        return device_description(device)
    return device_description(device) + f" x {workers.world} workers ({workers.backend}, {trainer.partition.describe()})"


def _views_for_workers(args: TrainArgs, explicit: set[str], workers) -> str:
    """A new run on several workers without --train.views-per-step: as many views per step as
    they need (atgs.train.distributed.views_that_work), set in ``args``; returns the start-up
    line's note of the choice ("" when none was made). A value given keeps its check."""
    from atgs.train.distributed import views_that_work

    if workers is None or "train.views_per_step" in explicit:
        return ""
    t = args.train
    views = views_that_work(t.views_per_step, workers.world, t.partition, t.time_groups, workers.nodes)
    if views == t.views_per_step:
        return ""
    args.train = replace(t, views_per_step=views)
    return f", {views} views per step (--train.views-per-step not given; {t.views_per_step} is too few for them)"


def run(args: TrainArgs, explicit: set[str] = frozenset()) -> dict:
    """Train; the first Ctrl-C during the steps finishes the current one, saves ckpt.pt and raises
    Interrupted. Then the final evaluation (a Ctrl-C there leaves the complete checkpoint).
    Under torchrun (several workers) this process trains its share (and scores its share of the
    periodic evaluations); rank 0 runs the final evaluation, writes and
    raises Interrupted, the others return (``result["stopped_early"]`` after a Ctrl-C)."""
    workers = join_workers(args)
    try:
        return _train(args, explicit, workers)
    finally:
        if workers is not None:
            signal.signal(signal.SIGTERM, signal.SIG_IGN)  # on the way out torchrun's SIGTERM is no news
            workers.close(together=sys.exc_info()[0] is None)  # (on an error the others may be gone)


def restarted_run(args: TrainArgs) -> bool:
    """True in a worker that torchrun restarted after a failure (--max-restarts) when --out holds a
    checkpoint of the run this start began or resumed: it continues that checkpoint, as --resume
    does. Any other checkpoint (the run an --overwrite start replaces, before the new run's first
    checkpoint) is left alone: the restart starts afresh, as the first start did. One line says
    which (rank 0)."""
    restart = int(os.environ.get("TORCHELASTIC_RESTART_COUNT", "0"))
    if restart <= 0:
        return False
    ckpt = args.out / "ckpt.pt"
    not_ours = _not_this_starts(args, ckpt)
    done = f"continuing from {ckpt}" if not_ours is None else f"{not_ours}: starting afresh, as the first start did"
    print(f"{PROG}: restarted by the launcher after a worker failed (restart {restart}); {done}", flush=True)
    return not_ours is None


def _not_this_starts(args: TrainArgs, ckpt: Path) -> str | None:
    """Why ``ckpt`` is not a checkpoint of this start's run, None when it is: a --resume start
    continues the run there; a fresh one wrote its start's id into its checkpoints (atgs.train.run_dir)."""
    from atgs.train.run_dir import run_id_of, start_id

    if args.resume:
        return None
    if not ckpt.is_file():
        return "no checkpoint written yet"
    if start_id() is None:  # (several machines without --rdzv-id: every start's id is "none")
        return f"{ckpt} cannot be told from another run's without torchrun's --rdzv-id (pass one to continue)"
    if run_id_of(ckpt) != start_id():
        return f"{ckpt} is another run's (this start wrote none yet)"
    return None


def _train(args: TrainArgs, explicit: set[str], workers) -> dict:
    if restarted_run(args):
        args.resume = True
    trainer = make_trainer(args, explicit, workers)
    notice = f"{PROG}: stopping after this step and saving a checkpoint (Ctrl-C again to abort)"
    with stop_on_sigint(notice if trainer.leads else "") as stop:
        result = trainer.run_steps(progress=args.progress, should_stop=stop)
    ckpt = trainer.run.ckpt_path
    if "stopped_early" in result:  # (every worker stopped after the same step)
        if not trainer.leads:
            return result
        if not result["steps"]:
            raise Interrupted(f"stopped before the first step; nothing was written to {args.out}")
        raise Interrupted(f"checkpoint of step {trainer.step} saved to {ckpt}; continue with "
                          f"atgs-train --out {args.out} --resume")
    ev = trainer.final_evaluation(args.out / "eval")  # the figure atgs-eval gives; every worker scores its frames
    if not trainer.leads:  # rank 0 writes and says what happened
        return result
    result["eval"] = ev
    trainer.run.write_result(result)
    ev = result.get("eval", {})
    # a scene without held-out cameras is scored on a training camera: say so, not "test"
    which = "test" if ev.get("on_test_cameras", True) else "training-view (no held-out camera)"
    print(f"{PROG}: done, {result['steps']} steps in {result['seconds']:.0f} s; "
          f"{which} PSNR {ev.get('psnr', float('nan')):.2f} dB ({ev.get('psnr_matched', float('nan')):.2f} dB "
          f"exposure-matched), SSIM {ev.get('ssim', float('nan')):.4f}; checkpoint {ckpt}")
    if result.get("camera_exposure"):
        print(f"{PROG}: {exposure_summary(result['camera_exposure'])}")
    return result


def exposure_summary(exposure: dict) -> str:
    """One line on the learned per-camera exposure: the spread of the cameras' mean gains."""
    mean_gain = {name: sum(e["gain"]) / 3 for name, e in exposure.items()}
    lo, hi = min(mean_gain, key=mean_gain.get), max(mean_gain, key=mean_gain.get)
    return (f"camera exposure: gains {mean_gain[lo]:.2f} ({lo}) to {mean_gain[hi]:.2f} ({hi}) of the "
            "training cameras' average, which held-out cameras and the viewer render")


def join_workers(args: TrainArgs):
    """Under torchrun (WORLD_SIZE > 1): this process's :class:`atgs.train.distributed.Workers`,
    with SIGTERM (the launcher stopping the others when one failed) as a one-line stop and, off
    rank 0, no progress and no stdout. None for one process."""
    from atgs.train.distributed import WorkerLost, Workers

    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return None
    if args.workers not in (1, world):
        raise ConfigError(f"--workers {args.workers} under a launcher that started {world} processes; pass one of them")
    workers = Workers.from_env(resolve_device(args.device, need_gsplat=True), args.worker_timeout)

    def stopped(signum: int, frame: object) -> None:
        ckpt = args.out / "ckpt.pt"
        kept = (f"{ckpt} holds the last checkpoint, --resume continues it" if ckpt.is_file()
                else "no checkpoint was written yet")
        raise WorkerLost(f"worker {workers.rank}: stopped by the launcher (another worker failed or the run was "
                         f"cancelled); {kept}")

    signal.signal(signal.SIGTERM, stopped)
    if not workers.leads:
        args.progress = False
        sys.stdout = open(os.devnull, "w")
    return workers


def launch_workers(argv: list[str], args: TrainArgs) -> int:
    """``atgs-train --workers N``: torchrun's launcher in this process (a standalone rendezvous on
    this machine) starts N workers that run atgs-train with the same flags. Settings N workers
    cannot train are refused before any starts; a worker killed or failing ends the others
    (torchrun) and this process with one line."""
    os.environ.setdefault("LOGLEVEL", "CRITICAL")  # torchrun's log lines (modules loaded later read it)
    from torch.distributed.elastic.multiprocessing.api import SignalException
    from torch.distributed.elastic.multiprocessing.errors import ChildFailedError
    from torch.distributed.run import get_args_parser, run as torchrun

    from atgs.train.distributed import check_settings, views_that_work

    for name in list(logging.root.manager.loggerDict):  # (and those loaded already): this process says what failed
        if name.startswith("torch.distributed"):
            logging.getLogger(name).setLevel(logging.CRITICAL)

    n = args.workers
    cfg = args.train
    if args.resume:  # the run's own settings
        from atgs.checkpoint import read_checkpoint
        from atgs.config_dict import from_dict

        cfg = from_dict(TrainConfig, read_checkpoint(resumed_checkpoint(args))["train_config"])
    given = given_flags(argv, "--train.")
    partition = args.train.partition if "partition" in given else cfg.partition
    groups = args.train.time_groups if "time-groups" in given else cfg.time_groups
    views = cfg.views_per_step
    if not args.resume and "views-per-step" not in given:  # (the workers choose as many as they need)
        views = views_that_work(views, n, partition, groups)
    check_settings(views, n, partition, groups)  # (one machine: one node)
    os.environ.setdefault("OMP_NUM_THREADS", str(max(1, (os.cpu_count() or 1) // n)))
    launcher = get_args_parser().parse_args(["--standalone", f"--nproc-per-node={n}",
                                             f"--max-restarts={args.max_restarts}", "--module", "atgs.cli.train", *argv])
    try:
        torchrun(launcher)
    except SignalException:  # Ctrl-C: torchrun passed it on; rank 0 said what it saved
        return EXIT_INTERRUPTED
    except ChildFailedError as e:
        return _failed_workers(e, args)
    return 0


def _failed_workers(error, args: TrainArgs) -> int:
    """The launcher's exit code when a worker failed: a worker killed by a signal (other than the
    SIGTERM with which torchrun stops the rest) in one line here; otherwise the first failed
    worker's code (it said why)."""
    from atgs.train.distributed import WorkerLost

    failures = sorted(error.failures.items())
    killed = [(rank, f) for rank, f in failures if f.exitcode < 0 and f.exitcode != -signal.SIGTERM]
    said = [(rank, f) for rank, f in failures if f.exitcode > 0]
    if killed or not said:
        rank, f = (killed or failures)[0]
        ckpt = args.out / "ckpt.pt"
        kept = (f"{ckpt} holds the last checkpoint; continue with {PROG} --out {args.out} --resume"
                if ckpt.is_file() else "no checkpoint was written yet")
        raise WorkerLost(f"worker {rank} (pid {f.pid}) was killed by {f.signal_name()}; the other workers "
                         f"stopped; {kept}")
    return said[0][1].exitcode


def main(argv: list[str] | None = None) -> int:
    process = argv is None  # the process's entry point (console script or python -m)
    argv = sys.argv[1:] if argv is None else argv

    def body() -> int | None:  # a bad flag is a one-line error too (atgs.config_checks)
        flags = current_spelling(argv)  # (the launcher's workers get the current spellings)
        args = parse(flags)
        if args.workers > 1 and int(os.environ.get("WORLD_SIZE", "1")) <= 1:
            return launch_workers(flags, args)
        # (--train.partition / --train.time-groups on a resume: the workers split the run from here on so)
        given = given_flags(flags, "--train.")
        partition = {f"train.{k.replace('-', '_')}" for k in ("partition", "time-groups", "views-per-step")
                     if k in given}
        result = run(args, explicit_model_flags(flags) | partition)
        return EXIT_INTERRUPTED if "stopped_early" in result else None  # (a worker other than rank 0)

    code = run_cli(PROG, body, process=process)
    if process and int(os.environ.get("WORLD_SIZE", "1")) > 1:
        # a torchrun worker ends now: in a slow interpreter teardown (its signal handlers reset)
        # the SIGTERM with which torchrun stops the others would read as "killed"
        _exit_now(code)
    return code


if __name__ == "__main__":
    sys.exit(main())
