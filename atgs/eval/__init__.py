"""Evaluation: image metrics (:mod:`atgs.eval.metrics`), LPIPS from local weights only
(:mod:`atgs.eval.lpips`) and the evaluation loop behind ``atgs-eval`` (:mod:`atgs.eval.evaluate`).

Submodules are imported on use so that ``from atgs.eval.metrics import ssim`` (the training
loss) does not pull in the rasterizer or PIL.
"""
