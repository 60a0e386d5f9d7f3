"""``atgs-train``: train ATGS on a prepared scene (or the built-in synthetic scene).

    atgs-train --data DIR --out DIR [--preset cpu-fast|cpu|cpu-accurate|paper] [--minutes M | --iterations N] [--resume]
               [--device auto|cpu|cuda] [--workers N]

Every model/trainer knob is a flag (``--model.*``, ``--train.*``; see ``atgs-train --help``);
flag defaults come from the chosen preset. Nothing in an existing ``--out`` changes before the new
run's first checkpoint (atgs.train.run_dir); Ctrl-C saves a checkpoint that ``--resume`` continues.

Several workers (atgs.train.distributed): ``torchrun --nproc-per-node N -m atgs.cli.train ...``
with the same flags, or ``atgs-train --workers N``, which runs torchrun's launcher in this process.
Rank 0 prints and writes the run's files; the others print only their errors.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
import logging
import os
from pathlib import Path
import signal
import sys

import tyro

from atgs.config_checks import ConfigError, above, at_least, check_fields
from atgs.device import DeviceName, auto_fallback_note, device_description, resolve_device
from atgs.errors import OutputError
from atgs.io.cache import cache_dir
from atgs.geometry.rig_check import sparse_rig_warning
from atgs.io.cli import EXIT_INTERRUPTED, Interrupted, _exit_now, run_cli, stop_on_sigint
from atgs.model.config import ModelConfig
from atgs.train.config import PRESET_NAMES, PresetName, TrainConfig, preset
from atgs.train.step_schedule import SCHEDULE_SETTINGS, schedule_for

PROG = "atgs-train"


@dataclass
class TrainArgs:
    out: Path = Path("runs/atgs")
    """Output directory: ckpt.pt, train_log.csv, config.json, result.json, eval/."""
    data: Path | None = None
    """Prepared scene directory (atgs-prepare); default: the built-in synthetic scene."""
    preset: PresetName = "cpu"
    """Configuration preset (fast -> accurate: cpu-fast, cpu, cpu-accurate; paper = GPU sizes)."""
    iterations: int | None = None
    """Run exactly this many training steps (the schedule sized to them, atgs.train.step_schedule;
    no time budget); with --resume: the new total. --train.iterations alone means the same."""
    minutes: float | None = None
    """Training time budget: the number of steps is sized from the measured step time and
    re-sized as the model grows, so that training (with its final evaluation) ends on time.
    Default: the preset's (cpu-fast 5, cpu 20, cpu-accurate 60 minutes; paper: 30,000 steps).
    With --resume: the new total (time already used counts)."""
    resume: bool = False
    """Continue the run in --out from its ckpt.pt (configuration from the checkpoint)."""
    overwrite: bool = False
    """Start a new run even if --out already holds a checkpoint (it is replaced at the first save)."""
    device: DeviceName = "auto"
    """Where to train: cuda (the GPU; gsplat rasterizes), cpu (the compiled CPU rasterizer),
    auto (cuda when torch sees a GPU and gsplat imports, else cpu). --resume may change it."""
    progress: bool = True
    cache_dir: Path = field(default_factory=cache_dir)
    """Where the built-in synthetic scene is cached (default: $ATGS_CACHE_DIR, else ~/.cache/atgs)."""
    synth_keyframes: int = 6
    """Keyframes of the built-in synthetic scene (when --data is not given)."""
    auto: bool = False
    """Measure the scene's motion and choose K, M, hash table size and spatial grid resolution
    from it (printed with the reasons); --model.* flags given explicitly still win."""
    workers: int = 1
    """Worker processes on this machine, each rendering its share of every step's views, their
    gradients summed (torch.distributed: gloo on the CPU, NCCL on CUDA; docs/training.md, "Several
    workers"). N > 1 runs torchrun's launcher here (as torchrun --nproc-per-node N -m
    atgs.cli.train would); without --train.views-per-step, a new run takes at least N views per
    step (one each; a value given must be at least N)."""
    max_restarts: int = 0
    """With --workers N: after a worker fails (killed, crashed, lost), torchrun restarts all of
    them this many times; the restarted workers continue from the last checkpoint of this start's
    run, as --resume does (steps after it are trained again), or start afresh when there is none
    (a replaced run's is not continued). 0: a failure stops the run with one line."""
    worker_timeout: float = 1800.0
    """Seconds a worker waits for the others in an exchange before it stops (several workers;
    rank 0's set-up of the velocities from optical flow must fit in it; a worker that dies is noticed at once)."""
    model: ModelConfig = field(default_factory=ModelConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def __post_init__(self) -> None:
        if self.iterations is not None and self.minutes is not None:
            raise ConfigError("--iterations and --minutes were both given; pass one (--iterations N runs exactly "
                              "N steps, --minutes M sizes the steps to M minutes)")
        check_fields(self, "--", {"iterations": at_least(1, "a step count"),
                                  "minutes": at_least(0, "a time budget", "0 runs the preset's fixed step count"),
                                  "workers": at_least(1, "a number of processes"),
                                  "max_restarts": at_least(0, "a number of restarts"),
                                  "worker_timeout": above(0, "seconds")})


def _scan(argv: list[str], flag: str) -> str | None:
    """Value of ``--flag X`` / ``--flag=X`` (read before tyro so that presets set defaults)."""
    for i, a in enumerate(argv):
        if a == flag and i + 1 < len(argv):
            return argv[i + 1]
        if a.startswith(flag + "="):
            return a.split("=", 1)[1]
    return None


def given_flags(argv: list[str], prefix: str) -> set[str]:
    """Flags under ``prefix`` given on the command line, as they follow it with '-' for '_'
    (``--train.lr.warmup_steps=9`` -> "lr.warmup-steps")."""
    return {a[len(prefix):].split("=", 1)[0].replace("_", "-") for a in argv if a.startswith(prefix)}


def parse(argv: list[str]) -> TrainArgs:
    """The arguments, with the preset's values as defaults and the step count's schedule: a step
    count (--iterations, or --train.iterations without a budget) sizes the schedule by the one
    rule (atgs.train.step_schedule), except the schedule flags given, which are kept at any step
    count (also when a --minutes budget re-sizes it)."""
    name = _scan(argv, "--preset") or "cpu"
    model, train = preset(name if name in PRESET_NAMES else "cpu")  # tyro reports an unknown name
    args = tyro.cli(TrainArgs, default=TrainArgs(preset=name if name in PRESET_NAMES else "cpu",
                                                 model=model, train=train), args=argv)
    given = given_flags(argv, "--train.")
    pinned = tuple(s for s in SCHEDULE_SETTINGS if s in given and s not in args.train.fixed_schedule)
    args.train = replace(args.train, fixed_schedule=args.train.fixed_schedule + pinned)
    budget = args.minutes if args.minutes is not None else args.train.minutes if "minutes" in given else 0.0
    if args.iterations is not None and budget > 0:
        raise ConfigError(f"--iterations and --train.minutes {budget:g} were both given; pass one")
    if args.iterations is None and "iterations" in given and not budget > 0:
        args.iterations = args.train.iterations  # without a budget, the raw field is a step count too
    if args.iterations is not None:
        args.train = schedule_for(replace(args.train, minutes=0.0), args.iterations)
    if args.minutes is not None:
        args.train = replace(args.train, minutes=args.minutes)
    return args


def load_scene(args: TrainArgs):
    from atgs.data.scene import PreparedScene

    if args.data is None:
        from atgs.data.synth.videos import ensure_default_scene

        print(f"{PROG}: no --data given; using the built-in synthetic scene (cached in {args.cache_dir})", flush=True)
        path = ensure_default_scene(args.cache_dir, keyframes=args.synth_keyframes, progress=args.progress)
    else:
        path = args.data
    return PreparedScene.load(path)


def explicit_model_flags(argv: list[str]) -> set[str]:
    """Model knobs given on the command line, as dotted field names ("hash.log2_table_size")."""
    return {name.replace("-", "_") for name in given_flags(argv, "--model.")}


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
    trainer.run.stage_config({"preset": args.preset, "data": str(args.data) if args.data else None,
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
          f"{which} PSNR {ev.get('psnr', float('nan')):.2f} dB, SSIM {ev.get('ssim', float('nan')):.4f}; "
          f"checkpoint {ckpt}")
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
        args = parse(argv)
        if args.workers > 1 and int(os.environ.get("WORLD_SIZE", "1")) <= 1:
            return launch_workers(argv, args)
        # (--train.partition / --train.time-groups on a resume: the workers split the run from here on so)
        given = given_flags(argv, "--train.")
        partition = {f"train.{k.replace('-', '_')}" for k in ("partition", "time-groups", "views-per-step")
                     if k in given}
        result = run(args, explicit_model_flags(argv) | partition)
        return EXIT_INTERRUPTED if "stopped_early" in result else None  # (a worker other than rank 0)

    code = run_cli(PROG, body, process=process)
    if process and int(os.environ.get("WORLD_SIZE", "1")) > 1:
        # a torchrun worker ends now: in a slow interpreter teardown (its signal handlers reset)
        # the SIGTERM with which torchrun stops the others would read as "killed"
        _exit_now(code)
    return code


if __name__ == "__main__":
    sys.exit(main())
