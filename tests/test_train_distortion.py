"""--train.lambda-distortion in a real training loop: it thins the rays' depth spread."""

import torch

from builders import growing_tiny_config, make_toy_scene
from atgs.render import rasterize_gaussians
from atgs.train.losses import depth_distortion
from atgs.train.trainer import Trainer


def _mean_distortion(tr: Trainer) -> float:
    """The loss's value over every training camera at frame 0, in the model's voxels."""
    model, vals = tr.model, []
    with torch.no_grad():
        for ci in tr.train_idx:
            cam = tr.cams[ci]
            dec = model.decode_frame(0, [cam], track=False)
            out = rasterize_gaussians(dec.gaussians, cam)
            vals.append(float(depth_distortion(out.alpha, out.depth, out.depth_sq, model.voxel_size)))
    return sum(vals) / len(vals)


def test_distortion_thins_the_surfaces_the_run_learns(tmp_path):
    scene = make_toy_scene(num_frames=4, num_cameras=5, width=40, height=32, keyframes=2)
    runs = {}
    for lam in (0.0, 5.0):
        m, t = growing_tiny_config(40)
        t.lambda_distortion = lam
        torch.manual_seed(0)
        tr = Trainer(scene, m, t, tmp_path / f"l{lam}")
        tr.train(progress=False, final_renders=False)
        runs[lam] = _mean_distortion(tr)
    assert runs[5.0] < 0.8 * runs[0.0], runs
