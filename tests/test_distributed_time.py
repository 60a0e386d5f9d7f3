"""Several workers partitioned by time (--train.partition time, atgs.train.partition.time): two gloo
workers on the CPU each hold their time segments' tables and the anchors their frames reach, keep
the shared parameters identical, write one checkpoint that one process loads, and resume 2 -> 1
and 1 -> 2. Equality with a one-process run is not expected: each worker draws its own views."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

from builders import growing_tiny_config, make_toy_scene
from test_distributed import _free_port, _spawn, _tensors

STEPS, HALF = 12, 6


def _scene():
    # 8 frames, 4 keyframes, 2 segments of 4 frames; a window of 3 keyframes: worker 0's frames
    # reach keyframes 0-2, worker 1's 1-3 (keyframes 1 and 2 shared, 0 and 3 owned)
    return make_toy_scene(num_frames=8, num_cameras=4, width=40, height=32, keyframes=4)


def _configs(partition: str = "time"):
    m, t = growing_tiny_config(STEPS)
    m.window, m.num_segments = 3, 2
    t.views_per_step, t.cameras_per_frame, t.random_background, t.camera_exposure = 2, 2, True, "on"
    t.partition = partition
    return m, t


def _trainer(out: Path, workers=None, partition: str = "time"):
    from atgs.train.trainer import Trainer

    m, t = _configs(partition)
    return Trainer(_scene(), m, t, out, progress=False, workers=workers)


def _join(rank: int, world: int, port: int):
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE=str(world),
                      LOCAL_RANK=str(rank), LOCAL_WORLD_SIZE=str(world))
    from atgs.train.distributed import Workers

    return Workers.from_env(torch.device("cpu"), timeout_s=60)


def _run_recorded(tr, stop_at=None) -> dict:
    """Run ``tr`` recording the hash rows its own views touched; returns what the checks read."""
    from atgs.train.partition import time as time_partition

    start = tr.model.hash.table.clone()
    touched = []
    keep_owned = time_partition.keep_owned

    def spy(views, n):
        touched.extend(rows for rows, _ in views.grads.get("hash", []))
        return keep_owned(views, n)

    time_partition.keep_owned = spy
    try:
        tr.run_steps(progress=False, stop_at=stop_at)
    finally:
        time_partition.keep_owned = keep_owned
    part = tr.partition.part
    m, n = tr.model, part.num_shared(tr.model)
    shared = {"spatial": m.spatial.table, "exposure": tr.exposure.table,
              **{f"decoder/{k}": v for k, v in m.decoder.state_dict().items()},
              **{name: getattr(m, name)[:n] for name in ("anchor_mu", "anchor_keyframe", "anchor_feature",
                                                          "anchor_log_scale", "anchor_velocity", "anchor_fade")},
              **{f"adam/{k}": getattr(tr.sparse_opt, k)["spatial"] for k in ("exp_avg", "exp_avg_sq", "steps")}}
    return {"segments": (part.segments.start, part.segments.stop), "num_shared": n,
            "num_anchors": m.num_anchors, "hash": m.hash.table.clone(), "start": start,
            "touched": torch.unique(torch.cat(touched)) if touched else torch.zeros(0, dtype=torch.int64),
            "tmlp_w1": m.tmlp_w1.clone(), "own_feature": m.anchor_feature[n:].clone(),
            "own_keyframe": m.anchor_keyframe[n:].clone(), "shared": {k: v.clone() for k, v in shared.items()}}


def _worker(rank: int, world: int, port: int, d: Path) -> None:
    """The time-partitioned run in two halves (its checkpoint at HALF for the 2 -> 1 resume), and
    the one-process checkpoint at HALF resumed on two workers partitioned by time (1 -> 2)."""
    from atgs.train import distributed
    from atgs.train.trainer import Trainer

    workers = _join(rank, world, port)
    try:
        tr = _trainer(d / "two", workers)
        tr.run_steps(progress=False, stop_at=HALF)
        tr.save(d / "two_half.pt")
        torch.save(_run_recorded(tr), d / f"worker{rank}.pt")
        tr.save(d / "two.pt")
        distributed.SEND_BYTES = 200  # the same state again, sent in runs of a few rows (one if wider)
        tr.save(d / "two_in_runs.pt")
        tr = Trainer.resume(_scene(), d / "one_half.pt", d / "one_then_two", workers=workers, partition="time")
        assert tr.model.hash.num_grids == 1 and tr.step == HALF
        tr.run_steps(progress=False)
        tr.save(d / "one_then_two.pt")
    finally:
        workers.close()


def _broken(rank: int, world: int, port: int, d: Path, variant: str) -> None:
    """The same run with a wrong exchange: an owned table reduced, or a shared one not."""
    from atgs.train.partition import time as time_partition

    if variant == "owned reduced":
        time_partition.EXCHANGED["hash"] = "all"
    else:
        del time_partition.EXCHANGED["spatial"]
    workers = _join(rank, world, port)
    try:
        tr = _trainer(d / variant, workers)
        torch.save(_run_recorded(tr), d / f"{variant}{rank}.pt")
    finally:
        workers.close()


def _check_partition(w: list[dict], ckpt: Path | None) -> None:
    """(a) each worker holds its segments only; the shared parameters agree bit for bit; rows its
    own views never touched keep their start; (b) the checkpoint's rows are the owners'."""
    per_grid = w[0]["hash"].shape[0]
    assert w[0]["segments"] == (0, 1) and w[1]["segments"] == (1, 2)
    assert w[1]["hash"].shape[0] == per_grid and w[0]["tmlp_w1"].shape[0] == w[1]["tmlp_w1"].shape[0] == 1
    for k in w[0]["shared"]:
        assert torch.equal(w[0]["shared"][k], w[1]["shared"][k]), f"shared {k} differs between the workers"
    for r in (0, 1):
        untouched = torch.ones(per_grid, dtype=torch.bool)
        untouched[w[r]["touched"]] = False
        assert untouched.any() and torch.equal(w[r]["hash"][untouched], w[r]["start"][untouched]), \
            f"worker {r}: rows its views never touched changed (another worker's gradients?)"
    if ckpt is None:
        return
    data = torch.load(ckpt, weights_only=True)
    model = data["model"]
    assert model["hash"].shape[0] == 2 * per_grid and model["tmlp_w1"].shape[0] == 2, "every segment, once"
    # the checkpoint: the segments in rank order, the shared anchors once, then each worker's own
    n = w[0]["num_shared"]
    assert n > 0 and w[0]["num_anchors"] > n and w[1]["num_anchors"] > n, "shared and own anchors on each"
    assert model["anchor_mu"].shape[0] == w[0]["num_anchors"] + w[1]["num_anchors"] - n
    assert torch.equal(model["hash"][:per_grid], w[0]["hash"]) and torch.equal(model["hash"][per_grid:], w[1]["hash"])
    assert torch.equal(model["tmlp_w1"][1:], w[1]["tmlp_w1"])
    own1 = w[1]["own_feature"].shape[0]
    assert torch.equal(model["anchor_feature"][-own1:], w[1]["own_feature"])
    assert set(w[0]["own_keyframe"].tolist()) == {0} and set(w[1]["own_keyframe"].tolist()) == {3}
    assert data["trainer"]["sparse_opt"]["exp_avg"]["hash"].shape == model["hash"].shape
    assert data["trainer"]["densify"]["anchor_count"].shape[0] == model["anchor_mu"].shape[0]


def test_two_workers_partitioned_by_time_hold_their_segments_share_the_rest_and_resume(tmp_path: Path) -> None:
    from atgs.checkpoint import load_model
    from atgs.train.trainer import Trainer

    one = _trainer(tmp_path / "one", partition="views")  # (one process: the partition does not matter)
    one.run_steps(progress=False, stop_at=HALF)
    one.save(tmp_path / "one_half.pt")
    _spawn(_worker, (2, _free_port(), tmp_path))
    w = [torch.load(tmp_path / f"worker{r}.pt", weights_only=True) for r in (0, 1)]
    _check_partition(w, tmp_path / "two.pt")
    small_runs, whole = (_tensors(torch.load(tmp_path / p, weights_only=True)) for p in ("two_in_runs.pt", "two.pt"))
    assert small_runs.keys() == whole.keys()
    for k, v in whole.items():
        if isinstance(v, torch.Tensor):
            assert v.dtype == small_runs[k].dtype and torch.equal(v, small_runs[k]), k

    model = load_model(tmp_path / "two.pt")  # (b) the gathered checkpoint in one process
    assert model.num_anchors > 100, "anchors grew (46 at the start): densification on the workers"
    for f in range(model.num_frames):
        g = model.gaussians_at(model.timeline.time_of_frame(f))
        assert len(g) > 0 and bool(torch.isfinite(g.means).all())
    tr = Trainer.resume(_scene(), tmp_path / "two.pt", tmp_path / "eval")
    assert tr.final_evaluation(None)["psnr"] > 10

    two_then_one = Trainer.resume(_scene(), tmp_path / "two_half.pt", tmp_path / "two_then_one")  # (c) 2 -> 1
    assert two_then_one.model.hash.num_grids == 2 and two_then_one.step == HALF
    two_then_one.run_steps(progress=False)
    assert two_then_one.step == STEPS
    one_then_two = torch.load(tmp_path / "one_then_two.pt", weights_only=True)  # 1 -> 2
    assert one_then_two["step"] == STEPS and one_then_two["model"]["hash"].shape == w[0]["hash"].repeat(2, 1).shape


@pytest.mark.parametrize("variant", ["owned reduced", "shared not reduced"])
def test_a_wrong_exchange_fails_the_checks(tmp_path: Path, variant: str) -> None:
    _spawn(_broken, (2, _free_port(), tmp_path, variant))
    w = [torch.load(tmp_path / f"{variant}{r}.pt", weights_only=True) for r in (0, 1)]
    with pytest.raises(AssertionError, match="changed" if variant == "owned reduced" else "differs"):
        _check_partition(w, None)


def test_atgs_train_partitioned_by_time_evaluates_the_gathered_model_and_resumes(toy_scene_dir, tmp_path):
    """The command line: --workers 2 --train.partition time to the end (periodic evaluations spread over the workers,
    its final evaluation of the gathered checkpoint, every frame), then resumed
    on two workers again."""
    import json

    from test_distributed import _start
    from test_cli_promises import _finish, _last_line

    out = tmp_path / "run"
    code, err = _finish(_start("--data", str(toy_scene_dir), "--out", str(out), "tiny", "--train.iterations",
                               "4", "--workers", "2", "--train.partition", "time", "--train.eval-every", "2"))
    assert code == 0 and "Traceback" not in err, err
    evaluated = [r.split(",") for r in (out / "train_log.csv").read_text().strip().splitlines()]
    assert evaluated[2][evaluated[0].index("eval_psnr")], "the periodic evaluation (spread over the workers) at step 2"
    result = json.loads((out / "result.json").read_text())
    assert result["eval"]["psnr"] > 5 and result["eval"]["views"] == 6, result["eval"]
    code, err = _finish(_start("--out", str(out), "--data", str(toy_scene_dir), "--resume", "--train.iterations", "6",
                               "--workers", "2", "--train.partition", "views"))
    # (the views partition shares the run's views per step, 1 here, between the workers: refused)
    assert code == 2 and "--train.views-per-step is 1" in _last_line(err), err
    code, err = _finish(_start("--out", str(out), "--data", str(toy_scene_dir), "--resume", "--train.iterations", "6",
                               "--workers", "2"))
    assert code == 0 and "Traceback" not in err, err
    data = torch.load(out / "ckpt.pt", weights_only=True)
    assert data["step"] == 6 and data["train_config"]["partition"] == "time"


def _eval_worker(rank: int, world: int, port: int, d: Path) -> None:
    """Each partition trained 3 steps, then the periodic and the final evaluation spread over the
    workers."""
    import json

    workers = _join(rank, world, port)
    try:
        out = {}
        for partition in ("time", "views"):
            tr = _trainer(d / partition, workers, partition=partition)
            tr.run_steps(progress=False, stop_at=3)
            out[partition] = {"ev": tr.periodic_evaluation(), "own": tr.own_eval_frames(),
                              "all": tr.eval_frames()}
            tr.save(d / f"{partition}.pt")
            out[partition]["final"] = tr.final_evaluation(d / f"{partition}-eval")  # rank 0: the figures
        (d / f"eval{rank}.json").write_text(json.dumps(out))
    finally:
        workers.close()


@pytest.fixture(scope="module")
def spread_evaluations(tmp_path_factory) -> tuple[Path, list[dict]]:
    """Two workers of each partition after 3 steps: their evaluations and checkpoints."""
    import json

    d = tmp_path_factory.mktemp("spread")
    _spawn(_eval_worker, (2, _free_port(), d))
    return d, [json.loads((d / f"eval{r}.json").read_text()) for r in (0, 1)]


def test_the_periodic_evaluation_is_spread_over_the_workers_and_scores_every_frame(spread_evaluations) -> None:
    """Each worker scores its share of the evaluation frames (by time: the frames its segments
    decode, so worker 1's frames count too); the summed scores are one process's evaluation of the
    gathered checkpoint over all of those frames."""
    from atgs.train.trainer import Trainer

    tmp_path, got = spread_evaluations
    for partition in ("time", "views"):
        a, b = got[0][partition], got[1][partition]
        assert a["all"] == b["all"] and len(a["all"]) > 2
        assert sorted(a["own"] + b["own"]) == a["all"] and a["own"] and b["own"], "every frame scored once"
        assert a["ev"] == b["ev"]  # (every worker gets the sums)
        one = Trainer.resume(_scene(), tmp_path / f"{partition}.pt", tmp_path / f"one-{partition}")
        ref = one.evaluate(frames=a["all"])
        assert a["ev"]["views"] == ref["views"] > 0
        assert a["ev"]["psnr"] == pytest.approx(ref["psnr"], rel=1e-4)
        assert a["ev"]["ssim"] == pytest.approx(ref["ssim"], rel=1e-4)
    assert max(got[1]["time"]["own"]) > max(got[0]["time"]["own"])  # worker 1 holds the later frames


def test_the_final_evaluation_is_spread_over_the_workers_and_writes_what_one_process_writes(spread_evaluations):
    """The final evaluation (every frame, full resolution, three pictures per camera): each
    worker scores the frames it holds, rank 0 writes the directory. Reference: one process
    evaluating the checkpoint the workers wrote (per_view.csv row by row, the same pictures)."""
    import csv
    import json

    from atgs.train.trainer import Trainer

    tmp_path, got = spread_evaluations
    for partition in ("time", "views"):
        assert got[1][partition]["final"] is None  # rank 0 reports
        one = Trainer.resume(_scene(), tmp_path / f"{partition}.pt", tmp_path / f"one-final-{partition}")
        ref = one.final_evaluation(tmp_path / f"one-{partition}-eval")
        spread, alone = tmp_path / f"{partition}-eval", tmp_path / f"one-{partition}-eval"
        cameras = len(one.test_idx or [0])
        assert got[0][partition]["final"]["views"] == ref["views"] == 8 * cameras  # every frame
        assert got[0][partition]["final"]["psnr"] == pytest.approx(ref["psnr"], rel=1e-4)
        rows = [list(csv.reader(open(d / "per_view.csv"))) for d in (spread, alone)]
        assert [r[:2] for r in rows[0]] == [r[:2] for r in rows[1]]  # the same views in the same order
        for a, b in zip(rows[0][1:], rows[1][1:]):
            assert [float(x) for x in a[2:4]] == pytest.approx([float(x) for x in b[2:4]], rel=1e-4)
        pictures = [sorted(p.relative_to(d).as_posix() for p in (d / "images").rglob("*.png")) for d in (spread, alone)]
        assert pictures[0] == pictures[1] and len(pictures[0]) == 3 * cameras
        summary = json.loads((spread / "summary.json").read_text())
        assert summary["num_views"] == ref["views"] and summary["settings"]["frames"] == list(range(8))
