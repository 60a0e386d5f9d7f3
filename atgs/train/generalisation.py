"""The warning when the periodic evaluation lags the training views by far.

Training reports the PSNR of the views it trains on; the periodic evaluation renders the held-out
cameras (or, without any, the first training camera) from every anchor, as atgs-eval and the
player do. A gap of many dB means the model fits what training shows and nothing else, and the
user should hear it during the run, not after 20 minutes of it.

The evaluation's figure is the exposure-matched one (docs/evaluation.md): the training views are
scored with their learned exposure, and a held-out camera's own exposure, which no training can
learn, is not the model's gap.
"""

from __future__ import annotations

GAP_DB = 10.0  # a held-out view this far below the training views is not ordinary overfitting


def evaluation_gap_warning(step: int, eval_psnr: float, train_psnr: float | None, on_test_cameras: bool) -> str | None:
    """The one-line warning for an evaluation (exposure-matched PSNR) ``GAP_DB`` or more below the
    training views, else None."""
    if train_psnr is None or not (train_psnr - eval_psnr >= GAP_DB):
        return None
    head = (f"warning: step {step}: the periodic evaluation gives {eval_psnr:.1f} dB (exposure-matched), "
            f"{train_psnr - eval_psnr:.1f} dB below the training views' {train_psnr:.1f} dB; ")
    if not on_test_cameras:  # the same camera: only a difference between the two decodes explains it
        return head + ("training and evaluation render this training camera differently (Gaussians that the "
                       "training decode leaves out reach it); please report it with the scene")
    return head + ("the model fits only the training views: Gaussians no training view shows stand in front of "
                   "the held-out cameras (floaters of a sparse rig, or cameras that see each other), or the "
                   "held-out cameras see what no training camera sees; look at a held-out view "
                   "(atgs-view CKPT) and at the coverage atgs-prepare reported")
