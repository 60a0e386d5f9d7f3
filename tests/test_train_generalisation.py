"""The warning when the periodic evaluation lags the training views by far."""

from atgs.train.config import preset
from atgs.train.generalisation import GAP_DB, evaluation_gap_warning
from atgs.train.trainer import Trainer
from builders import make_toy_scene


def test_gap_warning_names_the_cause_by_what_was_evaluated():
    assert evaluation_gap_warning(100, 25.0, 30.0, True) is None
    assert evaluation_gap_warning(100, 25.0, None, True) is None  # no training figure yet
    held_out = evaluation_gap_warning(100, 8.0, 8.0 + GAP_DB + 0.5, True)
    assert held_out is not None and "fits only the training views" in held_out and "step 100" in held_out
    same_camera = evaluation_gap_warning(100, 8.0, 30.0, False)
    assert same_camera is not None and "render this training camera differently" in same_camera
    assert "\n" not in held_out + same_camera


def test_a_run_whose_evaluation_lags_says_so_once_and_keeps_it_in_the_result(tmp_path, capsys, monkeypatch):
    scene = make_toy_scene(num_frames=4, num_cameras=4, width=32, height=24, keyframes=2)
    m, t = preset("tiny")
    t.iterations, t.eval_every, t.save_every = 12, 3, 0
    tr = Trainer(scene, m, t, tmp_path)
    # an evaluation far below anything the training views give: the warning, printed once
    monkeypatch.setattr(tr, "evaluate", lambda *a, **k: {"psnr": -60.0, "psnr_matched": -50.0, "ssim": 0.0, "views": 1,
                                                          "on_test_cameras": True})
    result = tr.run_steps(progress=False)
    err = capsys.readouterr()
    said = (err.out + err.err).count("the periodic evaluation gives -50.0 dB")
    assert said == 1 and len(result["warnings"]) == 1


def test_an_ordinary_run_warns_nothing(tmp_path):
    scene = make_toy_scene(num_frames=4, num_cameras=4, width=32, height=24, keyframes=2)
    m, t = preset("tiny")
    t.iterations, t.eval_every, t.save_every = 12, 4, 0
    result = Trainer(scene, m, t, tmp_path).run_steps(progress=False)
    assert "warnings" not in result


def test_a_held_out_cameras_own_exposure_is_not_a_lag(tmp_path, capsys, monkeypatch):
    """Plain PSNR far below the training views, the exposure-matched one close: no warning."""
    scene = make_toy_scene(num_frames=4, num_cameras=4, width=32, height=24, keyframes=2)
    m, t = preset("tiny")
    t.iterations, t.eval_every, t.save_every = 12, 3, 0
    tr = Trainer(scene, m, t, tmp_path)
    monkeypatch.setattr(tr, "evaluate", lambda *a, **k: {"psnr": -50.0, "psnr_matched": 60.0, "ssim": 0.0, "views": 1,
                                                          "on_test_cameras": True})
    assert "warnings" not in tr.run_steps(progress=False)
