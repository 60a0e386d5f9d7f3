"""Checkpoints: round trip, validation errors, atomic writes, exact resume."""

import pickle

import pytest
import torch

import atgs
from atgs.checkpoint import VERSION, CheckpointError, read_checkpoint, save_checkpoint
from builders import growing_tiny_config, make_toy_scene
from atgs.train.trainer import Trainer


@pytest.fixture(scope="module")
def scene():
    return make_toy_scene(num_frames=5, num_cameras=4, width=32, height=24, keyframes=3)


def test_round_trip_and_public_api(scene, tmp_path):
    m, t = growing_tiny_config(6)
    tr = Trainer(scene, m, t, tmp_path)
    tr.train(progress=False, final_renders=False)
    model = atgs.load(tmp_path / "ckpt.pt")
    assert model.num_frames == 5 and model.fps == 30.0 and model.num_keyframes == 3
    assert [c.name for c in model.cameras] == [c.name for c in scene.cameras]
    assert model.test_camera_names == scene.test_cameras
    for f in range(5):
        a, b = model.gaussians_at_frame(f), tr.model.gaussians_at_frame(f)
        for x, y in zip(a.as_tuple(), b.as_tuple()):
            assert torch.equal(x, y)
    assert model.window_at(0.5) == tr.model.window_at(0.5)
    data = read_checkpoint(tmp_path / "ckpt.pt")
    assert data["version"] == VERSION and data["time_range"] == [0.0, 4 / 30.0]
    assert not list(tmp_path.glob("*.tmp-*")), "no temporary files left behind"


def test_bad_files_give_clear_errors(tmp_path):
    with pytest.raises(CheckpointError, match="not found"):
        atgs.load(tmp_path / "missing.pt")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"\x00garbage" * 100)
    with pytest.raises(CheckpointError, match="corrupt"):
        atgs.load(junk)
    foreign = tmp_path / "foreign.pt"
    torch.save({"state_dict": {"w": torch.zeros(2)}}, foreign)
    with pytest.raises(CheckpointError, match="not an ATGS checkpoint"):
        atgs.load(foreign)
    newer = tmp_path / "newer.pt"
    save_checkpoint(newer, {"step": 0})
    d = torch.load(newer, weights_only=True)
    d["version"] = VERSION + 1
    torch.save(d, newer)
    with pytest.raises(CheckpointError, match="newer"):
        atgs.load(newer)
    # a pickle that would run code is refused by weights_only loading
    evil = tmp_path / "evil.pt"

    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    with open(evil, "wb") as fh:
        pickle.dump({"format": "atgs-checkpoint", "x": Evil()}, fh)
    with pytest.raises(CheckpointError, match="corrupt"):
        atgs.load(evil)


def test_truncated_checkpoint_and_existing_file_survives_failed_write(scene, tmp_path):
    m, t = growing_tiny_config(2)
    tr = Trainer(scene, m, t, tmp_path)
    tr.train(progress=False, final_renders=False)
    path = tmp_path / "ckpt.pt"
    raw = path.read_bytes()
    cut = tmp_path / "cut.pt"
    cut.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(CheckpointError, match="corrupt"):
        atgs.load(cut)
    with pytest.raises(Exception):
        save_checkpoint(path, {"bad": lambda: 0})  # unpicklable: the write fails
    assert path.read_bytes() == raw, "a failed write never destroys the previous checkpoint"
    assert not list(tmp_path.glob("*.tmp-*"))


def test_resume_continues_exactly(scene, tmp_path):
    m, t = growing_tiny_config(10)
    full = Trainer(scene, m, t, tmp_path / "full")
    full.train(progress=False, final_renders=False)
    m, t = growing_tiny_config(10)
    half = Trainer(scene, m, t, tmp_path / "half")
    half.train(progress=False, stop_at=5)
    assert half.step == 5
    resumed = Trainer.resume(scene, tmp_path / "half" / "ckpt.pt", tmp_path / "half")
    assert resumed.step == 5
    resumed.train(progress=False, final_renders=False)
    assert full.model.num_anchors == resumed.model.num_anchors
    assert not torch.equal(full.model.anchor_mu[:5], half.model.anchor_mu[:5]) or \
        full.model.num_anchors != 33, "anchors were grown/pruned during the run"
    a, b = full.model.state_dict(), resumed.model.state_dict()
    for k in a:
        if isinstance(a[k], torch.Tensor):
            assert torch.equal(a[k], b[k]), k
    for k in a["decoder"]:
        assert torch.equal(a["decoder"][k], b["decoder"][k]), k
    rows = (tmp_path / "half" / "train_log.csv").read_text().strip().splitlines()
    assert len(rows) == 11 and rows[-1].startswith("10,")
