"""The training loop: balanced view sampling, sparse/dense Adam, densification, robustness to
non-finite values, periodic evaluation (through atgs.eval), checkpoints and resume.

What the trainer needs around the loop lives next to it, one module each: the set-up from the
scene (``scene_setup``), the loss terms (``loss_terms``), the learning rates (``schedule``), the
schedule's sizing to a step count (``step_schedule``), the time budget (``budget``) and the files
of the output directory (``run_dir``), the types of a step (``step``). How the run is split among
processes is a strategy of ``partition`` (one process, or several workers partitioned by views,
by time or by both: ``Trainer(workers=...)``, atgs.train.distributed); the trainer asks it and
holds no branch of its own for workers.

Device: the model, optimizer states, densification statistics, image cache and everything a
step creates live on ``device``; rasterization goes through ``atgs.render`` (gsplat for CUDA
tensors). The random generator stays on the CPU, so a seed draws the same views, backgrounds and
growth candidates on every device, and checkpoints hold CPU tensors. torch's thread count is the
run's (``--train.threads``) while the trainer works and is restored when it returns."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import replace
import functools
import math
from pathlib import Path
import time
from typing import Protocol

import numpy as np
import torch

from atgs.cameras import Camera
from atgs.checkpoint import CheckpointError, model_from_checkpoint, read_checkpoint, save_checkpoint
from atgs.config_dict import from_dict, to_dict
from atgs.keyframe_cloud import PointCloud
from atgs.data.scene import resize_frame
from atgs.errors import UserError
from atgs.model.atgs_model import ATGSModel, Decoded, num_segments_for
from atgs.model.config import ModelConfig
from atgs.geometry.reach import REFRESH_STEPS as REACH_REFRESH_STEPS
from atgs.model.grids import grid_kernels
from atgs.progress import progress_bar
from atgs.render import RasterOutput, rasterize_gaussians, warm_up
from atgs.render.environment import EnvironmentMap
from atgs.threads import torch_threads
from atgs.timeline import evenly_spaced
from atgs.train.budget import TimeBudget
from atgs.train.config import TrainConfig
from atgs.train.densify import DensifyStats, prune_anchors, prune_final
from atgs.train.distributed import Workers
from atgs.train.partition import Partition, partition_of
from atgs.train.dropout import drop_gaussians, drop_rate, render_generator
from atgs.train.exposure import CameraExposure, measure_scene_exposure
from atgs.train.generalisation import evaluation_gap_warning
from atgs.train.loss_terms import LossInputs, RenderedView, total_loss, weighted_terms
from atgs.train.losses import psnr
from atgs.train.optim import SparseAdam, merge_rows
from atgs.train.step import StepResult, StepViews, View
from atgs.train.run_dir import RunDir
from atgs.train.sampling import ImageCache, SegmentSampler
from atgs.train.scene_setup import (check_backend, free_space_of, measured_depths_of, model_from_scene,
                                    settings_from_scene, velocities_from_flow)
from atgs.train.schedule import dense_lrs, sparse_lr
from atgs.train.step_schedule import schedule_for


class SceneData(Protocol):
    """What the trainer reads of a scene (``atgs.data.scene.PreparedScene`` and ``MemoryScene``
    provide it; tests/test_data_scene.py checks both)."""

    cameras: list[Camera]
    num_frames: int
    fps: float
    keyframes: list[int]
    test_cameras: list[str]
    bounds: np.ndarray | None  # (2, 3) min and max corner; None: the model takes the points' box
    motion_keyframes: list[int]  # points on moving content at extra keyframes (may be empty)

    @property
    def point_cloud(self) -> PointCloud: ...  # by keyframe (read one at a time)

    @property
    def motion_cloud(self) -> PointCloud: ...

    @property
    def measured_counts(self) -> list[int] | None: ...  # per keyframe, its first points measured

    @property
    def train_indices(self) -> list[int]: ...

    @property
    def test_indices(self) -> list[int]: ...

    def image(self, cam_index: int, frame: int) -> np.ndarray: ...

    def image_uint8(self, cam_index: int, frame: int) -> np.ndarray: ...


class NonFiniteError(UserError, RuntimeError):
    """Training diverged (too many non-finite steps in a row); the message names the fix."""


def _in_run_threads(method: Callable) -> Callable:
    """Run a Trainer method with the run's torch thread count (--train.threads), then restore
    torch's (nested calls keep it)."""
    @functools.wraps(method)
    def wrapper(self: "Trainer", *args, **kwargs):
        with self.run_threads():
            return method(self, *args, **kwargs)
    return wrapper


class Trainer:
    def __init__(self, scene: SceneData, model_cfg: ModelConfig, cfg: TrainConfig, out_dir: str | Path,
                 model: ATGSModel | None = None, device: torch.device | str = "cpu", progress: bool = True,
                 workers: Workers | None = None, sparse_state: dict | None = None,
                 partition: Partition | None = None) -> None:
        """``device``: where training runs (``atgs.device.resolve_device`` picks it for the CLI);
        a given ``model`` is moved there. ``progress``: a bar for the set-up's longer steps.
        ``workers``: this process's place among several training the run together
        (atgs.train.distributed; every worker builds its Trainer alike); None: one process.
        ``sparse_state``: the given model's sparse optimizer state (:meth:`resume`), taken over.
        ``partition``: how the run is split (atgs.train.partition; :meth:`resume` passes the one it
        read the checkpoint for); default: from ``workers`` and ``cfg``.
        The set-up, in order (each step one method below):"""
        self.scene, self.device, self.out = scene, torch.device(device), Path(out_dir)
        self.train_idx, self.test_idx = list(scene.train_indices), list(scene.test_indices)
        self._check(cfg, model_cfg)
        self.partition = partition_of(workers, cfg) if partition is None else partition
        # (with torch's own thread count, as these always ran: their sums are part of the run)
        self._resolve_scene_settings(cfg, None if model is None else model.environment)
        self._early_seconds = 0.0  # set-up a time budget pays for, spent before it exists
        self.run = RunDir(self.out)
        with self.run_threads():
            self._set_up_views()
            self._set_up_model(model_cfg, model)
            self._set_up_optimizers(sparse_state)
            self._set_up_step_state()
            self._set_up_images_and_exposure()
            self._set_up_loss_inputs()
            self._build_kernels()
            self._start_velocities(progress)
            self._set_up_budget()
            self.partition.replicate(self.model, self.exposure)  # every worker starts from rank 0's

    # --- set-up ------------------------------------------------------------------------------
    def _check(self, cfg: TrainConfig, model_cfg: ModelConfig) -> None:
        """Refuse bad settings before any work (fields may have been set after construction)."""
        cfg.validate()
        model_cfg.validate()
        check_backend(self.device, cfg.render_backend)

    def _resolve_scene_settings(self, cfg: TrainConfig, environment: EnvironmentMap | None) -> None:
        """Background and camera exposure from the scene, once for the run (scene_setup)."""
        self.cfg, self._environment, self.measured_exposure = settings_from_scene(self.scene, cfg, environment)

    def run_threads(self) -> AbstractContextManager:
        """torch's thread count of this run's work (--train.threads), restored afterwards."""
        return torch_threads(self.cfg.threads) if self.cfg.threads > 0 else nullcontext()

    def _set_up_views(self) -> None:
        """Training cameras at the training resolution, and the generator every draw comes from
        (each time group's own: the first's is the run's)."""
        s = self.cfg.resolution_scale
        self.cams = [c.scaled(s) if s != 1.0 else c for c in self.scene.cameras]
        self.train_slot = {ci: k for k, ci in enumerate(self.train_idx)}
        self.draw_seed = self.partition.draw_seed(self.cfg.seed)
        self.gen = torch.Generator(device="cpu").manual_seed(self.draw_seed)

    def _set_up_model(self, model_cfg: ModelConfig, model: ATGSModel | None) -> None:
        """A new model from the scene (on the CPU, then moved) or the given one, on the device;
        then this process's share of it."""
        fresh = model is None
        if fresh:
            segments = self.partition.new_model_segments(num_segments_for(model_cfg, self.scene.num_frames))
            model = model_from_scene(self.scene, model_cfg, self.train_idx, self.cfg.seed, segments,
                                     spread=self.partition.workers)
        self.model = model.to(self.device)
        self.model_cfg = self.model.cfg  # a loaded model may have switched features off
        self.model.test_camera_names = list(self.scene.test_cameras)
        self.model.background = tuple(float(c) for c in self.cfg.background)
        self.model.environment = self._environment
        self.scene_flow_stats: dict | None = None
        self._velocities_due = fresh and self.cfg.velocity_from_flow and self.model_cfg.anchor_velocity
        self.partition.take_share(self.model, functools.partial(self._measure_velocities, False))
        # measured before the first culled decode (atgs.geometry.reach): unknown reach culls nothing
        self.model.refresh_reach()

    def _set_up_optimizers(self, sparse_state: dict | None) -> None:
        """Sparse Adam for the tables (rows a step touches; ``sparse_state``: a resumed run's,
        of the rows this process kept), dense Adam for the decoder heads."""
        sparse_state = self.partition.held_optimizer_state(sparse_state)
        self.sparse_opt = SparseAdam(self.model.sparse_tensors(), eps=self.cfg.adam_eps, state=sparse_state)
        dec = self.model.decoder
        self.dense_opt = torch.optim.Adam(
            [{"params": list(getattr(dec, h).parameters()), "name": h} for h in dec.HEADS], lr=0.0,
            eps=self.cfg.adam_eps)

    def _set_up_step_state(self) -> None:
        """What a checkpoint carries besides the model and optimizers."""
        self.stats = DensifyStats.zeros(self.model.num_anchors, self.model_cfg.gaussians_per_anchor, self.device)
        self.sampler = SegmentSampler(self.model.timeline, self.train_idx, self.gen, self.partition.held_segments())
        self.grid_visits = torch.zeros(self.model.num_segments, dtype=torch.int64, device=self.device)
        self.step = self.bad_in_row = self.skipped = self.final_pruned = 0
        # Ctrl-C: the request polled during run_steps; several workers stop after the step at
        # whose exchange any of them had it (_agreed_stop)
        self._should_stop: Callable[[], bool] | None = None
        self._agreed_stop = False

    def _set_up_images_and_exposure(self) -> None:
        """The training-image cache, and the learned per-camera exposure when it is on."""
        self.images = ImageCache(self._load_image, self.cfg.image_cache_mb, self.device)
        self.exposure = (CameraExposure(len(self.train_idx), self.cfg.lr.exposure, self.device)
                         if self.cfg.camera_exposure == "on" else None)
        if self.exposure is not None and self.cfg.exposure_start_measured:  # (resume loads its own state)
            if self.measured_exposure is None:
                self.measured_exposure = measure_scene_exposure(self.scene)
            self.exposure.start_from(self.measured_exposure)

    def _set_up_loss_inputs(self) -> None:
        """What the loss terms need besides a view: the space the training cameras prove empty
        (only for --train.lambda-free-space) and the background colour."""
        self.free_space = (free_space_of(self.scene, [self.cams[i] for i in self.train_idx], self.device)
                           if self.cfg.lambda_free_space > 0 else None)
        self.measured_depths = None
        if self.cfg.lambda_ray_free_space > 0:
            t0 = time.perf_counter()
            self.measured_depths = measured_depths_of(self.scene, [self.cams[i] for i in self.train_idx],
                                                      lambda s, f: self._load_image(self.train_idx[s], f), self.device)
            self._early_seconds += time.perf_counter() - t0
        self.fixed_background = torch.tensor(self.cfg.background, dtype=torch.float32, device=self.device)

    def _build_kernels(self) -> None:
        """Compile the rasterizer now (gsplat's CUDA kernels take minutes on first use), and the
        grids' CPU kernels (the sparse optimizer built its own), not in the first step, where a
        time budget would pay for them."""
        warm_up(self.device, self.cfg.render_backend)
        grid_kernels(self.model.hash.table, self.model.hash.backend)

    def _start_velocities(self, progress: bool) -> None:
        """A new model's anchor velocities from optical flow (unless its partition measured them
        before it took its share): set-up a budget pays for."""
        self._measure_velocities(progress and self.leads)

    def _measure_velocities(self, progress: bool) -> None:
        """Once: a new model's velocities from optical flow (several workers: each measures its
        share of the keyframes, and all gather them)."""
        if not self._velocities_due:
            return
        self._velocities_due = False
        t0 = time.perf_counter()
        self.scene_flow_stats = velocities_from_flow(self.model, self.scene, self.train_idx, progress,
                                                     spread=self.partition.workers)
        self._early_seconds += time.perf_counter() - t0

    def _set_up_budget(self) -> None:
        """--train.minutes: the step count is sized from the measured pace (atgs.train.budget); the
        set-up it paid for so far counts as time used."""
        self.budget = (TimeBudget(60.0 * self.cfg.minutes, reserve_views=self.final_views(),
                                  max_view_cost=self.final_view_cap())
                       if self.cfg.minutes > 0 else None)
        if self.budget is not None:
            self.budget.used += self._early_seconds
        self.clock: Callable[[], float] = time.perf_counter  # seconds; tests drive a budget with a fake clock
        self._session_start: float | None = None  # clock() when run_steps began
        self._used_before = 0.0  # seconds of earlier run_steps calls of this trainer
        self._overhead = 0.0  # of those, seconds of periodic evaluations and saves (not step time)
        self._planned_once = False
        self.warnings: list[str] = []  # said during the run (atgs.train.generalisation), also in the result

    @property
    def leads(self) -> bool:
        """This process prints, evaluates and writes the run's files (one process, or rank 0)."""
        return self.partition.leads

    # --- data -------------------------------------------------------------------------------
    def _load_image(self, cam: int, frame: int) -> np.ndarray:
        c = self.cams[cam]
        return resize_frame(self.scene.image_uint8(cam, frame), c.width, c.height)

    def _background(self) -> "torch.Tensor | EnvironmentMap":
        """A random colour per step, else the run's background by direction or its colour."""
        if self.cfg.random_background:  # drawn on the CPU (the generator's device), then moved
            return torch.rand(3, generator=self.gen, device=self.gen.device).to(self.device)
        return self.model.environment or self.fixed_background

    # --- learning rates (atgs.train.schedule) ---------------------------------------------------
    def _expected_visits(self) -> int:
        segs = max(1, len(self.sampler.segments))
        return max(1, self.cfg.iterations * self.cfg.views_per_step // segs)

    def dense_lrs(self, step: int) -> dict[str, float]:
        return dense_lrs(self.cfg.lr, step, self.cfg.iterations)

    def sparse_lr(self, name: str, rows: torch.Tensor, step: int) -> float | torch.Tensor:
        visits = self.partition.segment_visits(self.grid_visits)  # (of the segments its tables hold)
        return sparse_lr(self.cfg.lr, name, rows, step, self.model, visits, self._expected_visits())

    # --- the loss (atgs.train.loss_terms) ---------------------------------------------------------
    def loss_terms(self, dec: Decoded, out, gt: torch.Tensor, view: RenderedView | None = None
                   ) -> dict[str, torch.Tensor]:
        """Each active term of one view's loss, weighted, by name (``view``: which camera and
        frame ``out`` is; the terms that need it are off without it)."""
        return weighted_terms(LossInputs(dec, out, gt, self.model, self.cfg, self.free_space, view,
                                         self.measured_depths))

    def compute_loss(self, dec: Decoded, out, gt: torch.Tensor, view: RenderedView | None = None) -> torch.Tensor:
        """One view's loss: the sum of :meth:`loss_terms`."""
        return total_loss(self.loss_terms(dec, out, gt, view))

    # --- one optimisation step ---------------------------------------------------------------
    @_in_run_threads
    def train_step(self) -> StepResult:
        """One step: ``views_per_step`` frames, each decoded once and rendered from
        ``cameras_per_frame`` training cameras, their mean loss back-propagated; then the
        partition's exchange (several workers: what the update needs of the others' views), the
        sparse and dense updates and, when due, densification."""
        self.dense_opt.zero_grad(set_to_none=True)
        views = StepViews()
        rate = drop_rate(self.cfg.drop_gaussians, self.step, self.cfg.iterations)
        for view in self.partition.views_of_step(self.cfg.views_per_step, functools.partial(self._draw_view, views)):
            if not self._learn_view(view, rate, views):
                views.bad = True
                break
        dense = [p for g in self.dense_opt.param_groups for p in g["params"]]
        dense += [self.exposure.table] if self.exposure is not None else []
        if self.partition.exchange(views, dense, self.model, self._asked_to_stop):
            self._agreed_stop = True
        if views.bad:
            return self._skip_step()
        self.bad_in_row = 0
        for m in set(views.segments):
            self.grid_visits[m] += 1
        self._apply_sparse(views.grads)
        self._apply_dense()
        if self.exposure is not None:
            self.exposure.step(self.cfg.grad_clip)
        self.step += 1
        if self.step % REACH_REFRESH_STEPS == 0:  # anchors no view decoded lately: their reach drifts
            self.model.refresh_reach()
        self._maybe_densify()
        means = views.means()
        if means is None:
            return StepResult(float("nan"), float("nan"), 0, False)
        return StepResult(means[0], means[1], means[2], False)

    def _draw_view(self, views: StepViews, v: int, ahead: bool) -> View:
        """The step's view ``v`` from the sampler (its segment noted in ``views``); ``ahead``: its
        cameras' random backgrounds drawn now too (else each as it renders)."""
        cis, f = self.sampler.next_views(self.cfg.cameras_per_frame)
        views.segments.append(self.model.timeline.segment_of_frame(f))
        backgrounds = [self._background() for _ in cis] if ahead and self.cfg.random_background else None
        return View(v, cis, f, backgrounds)

    def _learn_view(self, view: View, rate: float, views: StepViews) -> bool:
        """Decode the view's frame, render it from its cameras and back-propagate its renders'
        share of the step's mean loss (gradients and statistics into ``views`` and the
        densification statistics); False when the decode or the loss is not finite."""
        cams = [self.cams[ci] for ci in view.cams]
        dec = self.model.decode_frame(view.frame, cams, track=True)
        views.decoded.append(dec.active)
        # one host-device synchronisation for the five tensors
        if not bool(torch.stack([torch.isfinite(x).all() for x in dec.gaussians.as_tuple()]).all()):
            return False
        if len(dec.gaussians) == 0:  # nothing of the model in these views: nothing to learn
            return True
        outs = [self._render(dec, view, k, ci, cam, rate, views) for k, (ci, cam) in enumerate(zip(view.cams, cams))]
        total = functools.reduce(lambda a, b: a + b, (loss for loss, _, _ in outs))
        if not bool(torch.isfinite(total)):
            return False
        (total / (self.cfg.views_per_step * self.cfg.cameras_per_frame)).backward()  # (every worker's: they sum)
        q = self.model.cfg.gaussians_per_anchor
        for _, cam, out in outs:
            g2d = out.means2d.grad
            slots = self.stats.record(dec, g2d if g2d is not None else None, out.radii, cam.width, cam.height, q)
            if slots is not None:
                self.partition.note_positions(self.stats, slots, self.step * self.cfg.views_per_step + view.index)
        for s in dec.sparse:
            if s.leaf.grad is not None:
                views.grads.setdefault(s.name, []).append((s.rows, s.leaf.grad))
        return True

    def _render(self, dec: Decoded, view: View, k: int, ci: int, cam: Camera, rate: float,
                views: StepViews) -> tuple[torch.Tensor, Camera, RasterOutput]:
        """The view's ``k``-th camera (training camera ``ci``): its render of the decode (with
        Gaussian dropout at ``rate``) and its loss, noted in ``views``; returns (loss, cam, render)."""
        q = self.model.cfg.gaussians_per_anchor
        gt = self.images.get(ci, view.frame)
        shown = dec.gaussians if rate <= 0 else drop_gaussians(  # (a draw of its own: dropout.py)
            dec.gaussians, rate, render_generator(self.draw_seed, self.step, view.index, k, self.gen.device),
            dec.anchor_ids * q + dec.slot_ids, self.model.num_anchors * q)
        background = self._background() if view.backgrounds is None else view.backgrounds[k]
        out = rasterize_gaussians(shown, cam, background=background, backend=self.cfg.render_backend,
                                  near=self.model.near)
        out.means2d.retain_grad()
        if self.exposure is not None:  # the image as this camera exposed it
            out = replace(out, image=self.exposure.apply(out.image, self.train_slot[ci]))
        loss = self.compute_loss(dec, out, gt, RenderedView(cam, self.train_slot[ci], view.frame, shown,
                                                            {"near": self.model.near}))
        views.losses.append(loss.detach())  # read back once at the end of the step
        views.psnrs.append(psnr(out.image, gt))
        views.n_gauss += len(dec.gaussians)
        return loss, cam, out

    def _asked_to_stop(self) -> bool:
        """Ctrl-C was pressed here (polled; the partition says when the run stops)."""
        return self._should_stop is not None and self._should_stop()

    def _skip_step(self) -> StepResult:
        """A step with non-finite Gaussians or loss changes nothing; too many in a row stop the run."""
        self.skipped += 1
        self.bad_in_row += 1
        self.dense_opt.zero_grad(set_to_none=True)
        if self.exposure is not None:
            self.exposure.opt.zero_grad(set_to_none=True)
        if self.bad_in_row > self.cfg.max_bad_steps:
            raise NonFiniteError(f"{self.bad_in_row} consecutive steps had a non-finite loss or Gaussians "
                                 f"(step {self.step}); lower the learning rates or resume from the last checkpoint")
        self.step += 1
        return StepResult(float("nan"), float("nan"), 0, True)

    def _apply_sparse(self, grads: dict[str, list[tuple[torch.Tensor, torch.Tensor]]]) -> None:
        tables = self.model.sparse_tensors()
        for name, parts in grads.items():
            rows, g = merge_rows(parts)  # several views touched this table: gradients of shared rows summed
            # (non-finite entries zeroed, clipped per table to norm grad_clip)
            self.sparse_opt.step(name, tables[name], rows, g, self.sparse_lr(name, rows, self.step),
                                 clip=self.cfg.grad_clip)

    def _apply_dense(self) -> None:
        lrs = self.dense_lrs(self.step)
        for group in self.dense_opt.param_groups:
            group["lr"] = lrs[group["name"]]
            for p in group["params"]:
                if p.grad is not None:
                    torch.nan_to_num_(p.grad, nan=0.0, posinf=0.0, neginf=0.0)
            if self.cfg.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(group["params"], self.cfg.grad_clip)
        self.dense_opt.step()

    def _maybe_densify(self) -> None:
        d = self.cfg.densify
        stop = int(d.stop_fraction * self.cfg.iterations)
        if self.step == self.cfg.iterations and d.final_prune:
            self._final_prune(stop)
            return
        if not d.enabled or self.step < d.start or self.step > stop or self.step % d.interval:
            return
        with self._stats_of_all_views():
            self.partition.grow(self.model, self.stats, d, self.sparse_opt, self.gen, self.cfg.seed, self.step)
            prune_anchors(self.model, self.stats, d, self.sparse_opt)
        self.model.refresh_reach()  # the new anchors' reach, before a decode counts them as in view

    def _final_prune(self, stop: int) -> None:
        d = self.cfg.densify
        last = stop - stop % d.interval  # the last densification step reset the statistics
        if not d.enabled or last < d.start:
            last = 0
        # an anchor in some training view is active in >= 1/K of the frames: after
        # 2 * cameras * K steps, never having been decoded in view means it never will be
        need = 2 * len(self.train_idx) * self.model.num_keyframes
        with self._stats_of_all_views():
            self.final_pruned = prune_final(self.model, self.stats, d, self.sparse_opt, self.step - last >= need)

    def _stats_of_all_views(self) -> AbstractContextManager:
        """Inside: the densification statistics of every view so far (several workers: summed
        over them as the partition says)."""
        return self.partition.all_views_statistics(self.stats, self.model)

    # --- evaluation ---------------------------------------------------------------------------
    def eval_frames(self) -> list[int]:
        """The frames of the periodic evaluation: ``eval_max_frames`` evenly spaced over the
        capture. Several workers split them (:meth:`own_eval_frames`) and sum their scores."""
        n = self.model.timeline.num_frames
        return list(evenly_spaced(n, max(1, self.cfg.eval_max_frames)))

    def own_eval_frames(self, frames: Sequence[int] | None = None) -> list[int]:
        """This process's share of ``frames`` (default :meth:`eval_frames`; atgs.train.partition:
        partitioned by time, the frames its model decodes)."""
        return self.partition.own_frames(self.eval_frames() if frames is None else list(frames), self.model)

    @_in_run_threads
    def evaluate(self, out: Path | None = None, frames: Sequence[int] | None = None,
                 resolution_scale: float | None = None, images_per_camera: int | None = None,
                 spread: bool = False) -> dict | None:
        """PSNR and SSIM on the test cameras (or the first training camera, with its learned
        exposure, when there are none) through :func:`atgs.eval.evaluate.evaluate`, over
        ``frames`` (default :meth:`eval_frames`) at ``resolution_scale`` (default the training resolution). ``out``: also write that
        evaluation directory (per_view.csv, summary.json and ``images_per_camera`` comparison
        images per camera, default one per evaluated frame). ``spread`` (several workers, all
        call it): each scores its share of the frames (:meth:`own_eval_frames`), rank 0 writes
        and returns the whole evaluation, the others None."""
        from atgs.eval.evaluate import EvalConfig, evaluate

        cams = self.test_idx or self.train_idx[:1]
        frames = tuple(self.eval_frames() if frames is None else frames)
        if out is None:
            images_per_camera = 0
        elif images_per_camera is None:
            images_per_camera = len(frames)
        cfg = EvalConfig(frames=frames, cameras=tuple(self.scene.cameras[i].name for i in cams),
                         images_per_camera=images_per_camera, lpips=False,
                         resolution_scale=self.cfg.resolution_scale if resolution_scale is None else resolution_scale,
                         backend=self.cfg.render_backend, progress=False)
        # a training camera is compared as it was exposed (held-out cameras get the average exposure)
        exposure = self.exposure if not self.test_idx else None

        def as_exposed(ci: int, img: torch.Tensor) -> torch.Tensor:
            return exposure.apply(img, self.train_slot[ci])

        share = self.partition.evaluation_share(frames, self.model) if spread else None
        res = evaluate(self.model, self.scene, cfg, out, background=self.model.environment or self.cfg.background,
                       camera_transform=as_exposed if exposure is not None else None, share=share)
        if res is None:  # (spread: another worker's result)
            return None
        return {"psnr": res.mean("psnr"), "psnr_matched": res.mean("psnr_matched"), "ssim": res.mean("ssim"),
                "views": res.summary["num_views"],
                "on_test_cameras": bool(self.test_idx)}

    def final_views(self) -> int:
        """Views the final evaluation renders: every frame of each test camera."""
        return len(self.test_idx or self.train_idx[:1]) * self.model.num_frames

    def final_view_cap(self) -> float:
        """The most the budget reserves a final-evaluation view, in steps: one, or the pixels a
        full-size view has more than a training view (atgs.train.budget)."""
        return max(1.0, self.cfg.resolution_scale ** -2)

    @_in_run_threads
    def final_evaluation(self, out: Path | None) -> dict | None:
        """What ``atgs-eval`` reports by default (every frame of the test cameras at full
        resolution, three comparison images per camera; LPIPS aside), so the figure that
        atgs-train prints at the end is the figure atgs-eval gives for the same checkpoint.
        Several workers (all call it): each scores its frames with the model it holds (partitioned
        by time: its segments' frames; no worker loads the whole model), rank 0 writes ``out`` and
        returns the figures, the others None."""
        return self.evaluate(out, frames=range(self.model.num_frames), resolution_scale=1.0, images_per_camera=3,
                             spread=True)

    # --- checkpoints ----------------------------------------------------------------------------
    def checkpoint_payload(self) -> dict:
        """What ``ckpt.pt`` holds (several workers: :meth:`save` sums the statistics first)."""
        m = self.model
        return {
            "model_config": to_dict(self.model_cfg), "train_config": to_dict(self.cfg),
            "cameras": [c.to_dict() for c in m.cameras], "test_cameras": list(self.scene.test_cameras),
            "num_frames": m.num_frames, "fps": m.fps,
            "time_range": [0.0, (m.num_frames - 1) / m.fps if m.fps > 0 else 0.0],
            "keyframes": m.timeline.keyframe_frames(), "step": self.step, "model": m.state_dict(),
            "data_dir": str(getattr(self.scene, "root", "") or ""),
            "environment": None if m.environment is None else m.environment.to_state(),
            "trainer": {
                "sparse_opt": self.sparse_opt.state_dict(), "dense_opt": self.dense_opt.state_dict(),
                "densify": self.stats.state_dict(), "sampler": self.sampler.state_dict(),
                "grid_visits": self.grid_visits.clone(), "generator": self.gen.get_state(),
                "skipped": self.skipped, "bad_in_row": self.bad_in_row,
                "budget": None if self.budget is None else self.budget.state_dict(self._time_used(),
                                                                                     self._overhead_used()),
                "exposure": None if self.exposure is None else self.exposure.state_dict(),
            },
        }

    def save(self, path: Path | None = None) -> Path:
        """Write the resumable checkpoint: by default the run's ``ckpt.pt`` (the first one also
        commits config.json and the log, see RunDir), or a copy at ``path``. Several workers: all
        call it (the statistics are summed over them; the partition gathers the payload), rank 0
        writes."""
        with self._stats_of_all_views():
            payload = self.partition.payload(self.checkpoint_payload, self.model, self.sparse_opt, self.stats,
                                             self.grid_visits)
            if payload is None:  # (a worker that does not write)
                return self.run.ckpt_path if path is None else Path(path)
            if path is None:
                return self.run.save_checkpoint(payload)
            save_checkpoint(path, payload)
            return Path(path)

    @classmethod
    def resume(cls, scene: SceneData, path: str | Path, out_dir: str | Path,
               iterations: int | None = None, minutes: float | None = None,
               device: torch.device | str = "cpu", workers: Workers | None = None,
               partition: str | None = None, time_groups: int | None = None) -> "Trainer":
        """Continue the run of checkpoint ``path`` on ``device`` (any: checkpoints hold CPU tensors
        and the optimizer and densification state move with the model) and on any number of
        ``workers``. ``iterations``: a new total step count (and no time budget; the schedule
        sized to it as ``--train.iterations`` sizes it); ``minutes``: a new total time budget (the
        time already used counts); ``partition`` and ``time_groups``: how several workers split
        the run from here (default: as it was saved; a checkpoint of any partition resumes with
        any). The partition reads its share of the checkpoint; the trainer loads what it read."""
        mapped = read_checkpoint(path, mmap=True)  # (its configuration; a worker's rows when it keeps a share)
        if mapped.get("trainer") is None:
            raise CheckpointError(f"{path}: checkpoint has no optimizer state and cannot be resumed")
        cfg = _resumed_config(mapped, iterations, minutes, partition, time_groups)
        if int(mapped["num_frames"]) != scene.num_frames:
            raise CheckpointError(f"{path}: checkpoint has {mapped['num_frames']} frames, the scene "
                                  f"{scene.num_frames}; resume with the same --data")
        split = partition_of(workers, cfg)
        data, segments = split.checkpoint_share(path, mapped)
        tr = cls(scene, from_dict(ModelConfig, data["model_config"]), cfg, out_dir,
                 model=model_from_checkpoint(data, path, device, segments), device=device, workers=workers,
                 sparse_state=data["trainer"]["sparse_opt"], partition=split)
        tr._load_state(data)
        return tr

    def _load_state(self, data: dict) -> None:
        """A resumed run's trainer state (besides the model and the sparse optimizer), as its
        partition carries it on."""
        st = data["trainer"]
        self.dense_opt.load_state_dict(st["dense_opt"])  # torch.optim moves the state to the parameters
        if self.exposure is not None and st.get("exposure") is not None:
            self.exposure.load_state_dict(st["exposure"])
        self.stats = self.partition.resumed_statistics(st["densify"], self.model, self.device)
        self.sampler.load_state_dict(st["sampler"])
        self.grid_visits = st["grid_visits"].to(self.device, copy=True)
        self.partition.resume_generator(self.gen, st["generator"], self.cfg.seed, int(data["step"]))
        self.skipped, self.bad_in_row = int(st["skipped"]), int(st["bad_in_row"])
        self.step = int(data["step"])
        self.run = RunDir(self.out, resume_step=self.step, run_id=data.get("run_id"))  # (the run it continues)
        saved = st.get("budget")
        if self.budget is not None and saved is not None:  # the time used so far counts
            self.budget = TimeBudget.resumed(saved, 60.0 * self.cfg.minutes)
            self.budget.reserve_views = self.final_views()
            self.budget.max_view_cost = self.final_view_cap()
            left = self.budget.steps_left()
            if left is not None:  # provisional plan at the last pace; re-planned after calibration
                self.cfg = schedule_for(self.cfg, max(1, self.step + left))

    # --- time budget -------------------------------------------------------------------------------
    def _time_used(self) -> float:
        """Training seconds of this run so far, earlier sessions (resumes) included."""
        before = self._used_before + (self.budget.used if self.budget is not None else 0.0)
        now = 0.0 if self._session_start is None else self.clock() - self._session_start
        return before + now

    def _overhead_used(self) -> float:
        """The part of :meth:`_time_used` that went to periodic evaluations and checkpoints."""
        return self._overhead + (self.budget.overhead if self.budget is not None else 0.0)

    def _follow_budget(self, bar) -> None:
        """Re-size the schedule to the time left (no-op without --train.minutes)."""
        if self.budget is None:
            return
        used, overhead = self._time_used(), self._overhead_used()
        used, overhead = self.partition.agreed_floats([used, overhead])  # (rank 0's clock on several workers)
        n = self.budget.plan(self.step, used, self.cfg.iterations, overhead)
        if self.budget.wants_view_cost:
            self._time_final_evaluation()
        if n is None:
            return
        first = self.budget.pace > 0 and self._planned_once is False
        self.cfg = schedule_for(self.cfg, max(n, self.step))  # as --train.iterations would size it
        if self.step >= n and self.cfg.densify.final_prune:  # out of time: the run ends at this step
            self._final_prune(int(self.cfg.densify.stop_fraction * self.cfg.iterations))
        bar.total = n
        bar.refresh()
        if first:
            self._planned_once = True
            bar.write(f"atgs-train: {self.budget.seconds / 60:.4g} min budget: {self.budget.pace:.3f} s per step "
                      f"-> about {n} steps (re-sized as the model grows), {self.budget.reserve():.0f} s kept for "
                      f"the final evaluation of {self.budget.reserve_views} views")

    def _time_final_evaluation(self) -> None:
        """The budget's reserve for the final evaluation, measured: that evaluation (full
        resolution, no pictures) on two of this process's frames, each timed alone, the faster
        per view (rank 0's figure on several workers). The first evaluation of a run builds what
        later ones reuse: on the 27-camera stage it took three times the steady cost. Their
        seconds are overhead, as a periodic evaluation's are."""
        cams = len(self.test_idx or self.train_idx[:1])
        times = []
        for frame in self.own_eval_frames()[:2]:
            t = self.clock()
            self.evaluate(frames=[frame], resolution_scale=1.0)
            times.append(self.clock() - t)
        self._overhead += sum(times)
        (per_view,) = self.partition.agreed_floats([min(times) / cams if times else 0.0])
        self.budget.measured_view(per_view)

    # --- the loop -------------------------------------------------------------------------------------
    def train(self, progress: bool = True, final_renders: bool = True, stop_at: int | None = None,
              should_stop: Callable[[], bool] | None = None) -> dict:
        """:meth:`run_steps`, then the final evaluation (``result["eval"]``; written to ``eval/``
        with ``final_renders``) unless the run stopped early."""
        result = self.run_steps(progress, stop_at, should_stop)
        if "stopped_early" not in result and (final_renders or self.cfg.eval_every > 0):
            ev = self.final_evaluation(self.out / "eval" if final_renders else None)  # (every worker)
            if self.leads:
                result["eval"] = ev
        return result

    @_in_run_threads
    def run_steps(self, progress: bool = True, stop_at: int | None = None,
                  should_stop: Callable[[], bool] | None = None) -> dict:
        """Train until ``cfg.iterations`` with periodic evaluation and checkpoints, then save
        ``ckpt.pt``. It stops early, as if killed there (checkpoint written,
        ``result["stopped_early"]`` = the step), at step ``stop_at`` or after the step at which
        ``should_stop()`` turns true (Ctrl-C; several workers: on any of them). (``self.cfg`` is
        read afresh every step: a time budget re-sizes its schedule.)"""
        t0 = self._session_start = self.clock()
        start = self.step
        bar = progress_bar(self.cfg.iterations, "atgs-train", unit="step", enabled=progress, initial=start)
        ema = _Ema()
        # steps of the last evaluation and save: a time budget may resize the intervals mid-run,
        # so "due" is "an interval has passed", not "the step is a multiple of it"
        self._last_eval = start - start % self.cfg.eval_every if self.cfg.eval_every > 0 else start
        self._last_save = start - start % self.cfg.save_every if self.cfg.save_every > 0 else start
        self._should_stop, self._agreed_stop = should_stop, False
        try:
            while (self.step < (self.cfg.iterations if stop_at is None else min(stop_at, self.cfg.iterations))
                   and not self._stop_requested()):
                r = self.train_step()
                if not r.skipped and math.isfinite(r.loss):
                    ema.add(r.loss, r.psnr)
                row = {"step": self.step, "loss": f"{r.loss:.6f}", "psnr": f"{r.psnr:.3f}",
                       "anchors": self.model.num_anchors, "gaussians": r.gaussians,
                       "seconds": f"{self.clock() - t0:.2f}", "skipped": self.skipped,
                       "eval_psnr": "", "eval_ssim": ""}
                self._evaluate_if_due(row, ema.psnr, bar)
                if self.leads:
                    self.run.log(row)
                self._save_if_due()
                bar.update(1)
                self._follow_budget(bar)
                if self.step % 5 == 0 or self.step == self.cfg.iterations:
                    bar.set_postfix(loss=f"{ema.loss or float('nan'):.4f}", psnr=f"{ema.psnr or float('nan'):.2f}",
                                    anchors=self.model.num_anchors, gs=r.gaussians, refresh=False)
        finally:
            bar.close()
            self._should_stop = None
        seconds = self.clock() - t0
        self._session_start = None
        self._used_before = self._used_before + seconds
        stopped_early = self.step < self.cfg.iterations
        if self.step > start or not stopped_early:  # a stop before any step has nothing new to save
            self.save()
        result = self._result(self.step - start, seconds)
        if stopped_early:
            result["stopped_early"] = self.step
        return result

    def _stop_requested(self) -> bool:
        """Ctrl-C: one process polls its request; several workers stop after the step at whose
        exchange any of them had one (so all stop after the same step)."""
        return self.partition.stop_requested(self._asked_to_stop, self._agreed_stop)

    def _due(self, every: int, last: int) -> bool:
        """An interval has passed since ``last``, and the run does not end at this step."""
        return every > 0 and self.step - last >= every and self.step < self.cfg.iterations

    def _evaluate_if_due(self, row: dict, ema_psnr: float | None, bar) -> None:
        """The periodic evaluation (into the log ``row``), and the warning it may raise once."""
        if not self._due(self.cfg.eval_every, self._last_eval):
            return
        self._last_eval = self.step
        t_eval = self.clock()
        ev = self.periodic_evaluation()
        self._overhead += self.clock() - t_eval  # not step time: the budget's pace excludes it
        if not self.leads:  # rank 0 logs it
            return
        row["eval_psnr"], row["eval_ssim"] = f"{ev['psnr']:.3f}", f"{ev['ssim']:.4f}"
        warning = evaluation_gap_warning(self.step, ev["psnr_matched"], ema_psnr, ev["on_test_cameras"])
        if warning is not None and not self.warnings:  # once a run: the log has every figure
            self.warnings.append(warning)
            bar.write(warning)

    def periodic_evaluation(self) -> dict:
        """:meth:`evaluate` as the periodic evaluation runs it: spread over the workers (each
        scores its share of the frames, a worker of the time partition those its model decodes,
        so every frame is scored; rank 0 takes the mean over all views, as one process does),
        its figures on every worker."""
        return self.partition.on_every_worker(self.evaluate(spread=True), bool(self.test_idx))

    def _save_if_due(self) -> None:
        if not self._due(self.cfg.save_every, self._last_save):
            return
        self._last_save = self.step
        t_save = self.clock()
        self.save()
        self._overhead += self.clock() - t_save

    def _result(self, steps: int, seconds: float) -> dict:
        """What run_steps returns (and atgs-train writes to result.json, with the evaluation)."""
        result = {"steps": steps, "seconds": seconds, "anchors": self.model.num_anchors,
                  "skipped": self.skipped, "final_pruned": self.final_pruned}
        if self.budget is not None:
            result["budget_seconds"] = self.budget.seconds
            result["seconds_used"] = self._time_used()
            result["seconds_per_step"] = self.budget.pace
        if self.exposure is not None:  # per training camera, relative to their average
            gains, biases = self.exposure.gains_biases()
            names = [self.scene.cameras[i].name for i in self.train_idx]
            result["camera_exposure"] = {n: {"gain": [round(float(x), 4) for x in g], "bias": [round(float(x), 4) for x in b]}
                                         for n, g, b in zip(names, gains.cpu(), biases.cpu())}
        if self.scene_flow_stats is not None:  # anchors tracked / measured / given a velocity
            result["scene_flow"] = dict(self.scene_flow_stats)
        if self.warnings:
            result["warnings"] = list(self.warnings)
        traffic = self.partition.summary()  # what several workers exchanged (atgs.train.distributed.Traffic)
        if traffic is not None:
            result["workers"] = traffic
        return result


def _resumed_config(data: dict, iterations: int | None, minutes: float | None, partition: str | None,
                    time_groups: int | None) -> TrainConfig:
    """The training configuration a checkpoint's run continues with (see :meth:`Trainer.resume`)."""
    cfg = from_dict(TrainConfig, data["train_config"])
    # the saved background is the colour the run trained over (resolved at its start); older
    # checkpoints lack the flag and would otherwise switch to the mean colour mid-run
    cfg.background_from_images = False
    if iterations is not None:
        cfg = schedule_for(replace(cfg, minutes=0.0), iterations)
    if minutes is not None:
        cfg = replace(cfg, minutes=minutes)
    if partition is not None:
        cfg = replace(cfg, partition=partition)
    if time_groups is not None:
        cfg = replace(cfg, time_groups=time_groups)
    return cfg


class _Ema:
    """Running averages of the training loss and PSNR for the progress bar (0.9 decay)."""

    def __init__(self) -> None:
        self.loss: float | None = None
        self.psnr: float | None = None

    def add(self, loss: float, psnr: float) -> None:
        self.loss = loss if self.loss is None else 0.9 * self.loss + 0.1 * loss
        self.psnr = psnr if self.psnr is None else 0.9 * self.psnr + 0.1 * psnr
