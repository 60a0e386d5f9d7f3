"""psnr_matched (atgs/eval/exposure_match.py): each camera's gain and bias per channel fitted by
least squares over its views, checked against a dense numpy fit over the stacked pixels, an
analytic exposure that it must undo exactly, and through evaluate() on a scene whose held-out
camera records the truth under its own exposure."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from atgs.eval.evaluate import evaluate
from atgs.eval.exposure_match import add_matched_psnr, fit_camera, matched_psnr, view_sums
from test_eval import FakeModel, FakeScene, fast_cfg, make_cameras, make_gaussians, moving, render


def dense_reference(views: dict[str, list[tuple[np.ndarray, np.ndarray]]]) -> dict[tuple[str, int], float]:
    """Per camera: stack every view's pixels, lstsq per channel, apply, PSNR per view."""
    out = {}
    for cam, pairs in views.items():
        xs = np.concatenate([x.reshape(-1, 3) for x, _ in pairs]).astype(np.float64)
        ys = np.concatenate([y.reshape(-1, 3) for _, y in pairs]).astype(np.float64)
        coef = [np.linalg.lstsq(np.stack([xs[:, c], np.ones(len(xs))], 1), ys[:, c], rcond=None)[0] for c in range(3)]
        for k, (x, y) in enumerate(pairs):
            fitted = np.stack([x[..., c] * coef[c][0] + coef[c][1] for c in range(3)], -1).astype(np.float64)
            out[(cam, k)] = -10 * math.log10(float(((fitted - y) ** 2).mean()))
    return out


def test_matches_a_dense_least_squares_fit() -> None:
    rng = np.random.default_rng(0)
    views = {cam: [(rng.random((9, 13, 3)).astype(np.float32), rng.random((9, 13, 3)).astype(np.float32))
                   for _ in range(n)] for cam, n in (("a", 3), ("b", 2))}
    rows = [{"camera": cam, "frame": k, "_exposure_sums": view_sums(torch.from_numpy(x), torch.from_numpy(y))}
            for cam, pairs in views.items() for k, (x, y) in enumerate(pairs)]
    fits = add_matched_psnr(rows)
    expect = dense_reference(views)
    for r in rows:
        assert "_exposure_sums" not in r
        assert r["psnr_matched"] == pytest.approx(expect[(r["camera"], r["frame"])], abs=1e-6)
    assert set(fits) == {"a", "b"} and len(fits["a"]["gain"]) == 3


def test_an_exposure_is_undone_exactly() -> None:
    rng = np.random.default_rng(1)
    gain, bias = np.array([1.3, 0.8, 1.1]), np.array([0.02, -0.05, 0.0])
    xs = [rng.uniform(0.1, 0.6, (8, 8, 3)) for _ in range(4)]
    sums = [view_sums(torch.from_numpy(x), torch.from_numpy(x * gain + bias)) for x in xs]
    g, b = fit_camera(sums)
    assert np.allclose(g, gain, atol=1e-9) and np.allclose(b, bias, atol=1e-9)
    assert all(matched_psnr(s, g, b) > 150 for s in sums)
    # a render that does not vary: gain 1, the mean difference as bias
    flat = [view_sums(torch.full((4, 4, 3), 0.5), torch.from_numpy(rng.random((4, 4, 3))))]
    g, b = fit_camera(flat)
    assert g == [1.0, 1.0, 1.0] and all(math.isfinite(v) for v in b)


def test_evaluate_scores_a_held_out_camera_under_its_own_exposure() -> None:
    """The held-out camera records the truth 25 % brighter and offset: plain PSNR falls to what the
    exposure costs, psnr_matched stays near perfect; the other camera is unchanged."""
    cams = make_cameras()
    truth = make_gaussians(0)

    class ExposedScene(FakeScene):
        def image(self, cam_index: int, frame: int) -> np.ndarray:
            img = render(moving(self.truth, frame), self.cameras[cam_index]).numpy()
            return np.clip(img * 1.25 + 0.03, 0, 1) if cam_index == 1 else img

    scene = ExposedScene(truth, cams, test_indices=[1, 2])
    res = evaluate(FakeModel(truth, cams), scene, fast_cfg())
    by_cam = res.summary["per_camera"]
    assert by_cam["cam01"]["psnr"] < 35 and by_cam["cam01"]["psnr_matched"] > by_cam["cam01"]["psnr"] + 10
    assert math.isinf(by_cam["cam02"]["psnr"]) and by_cam["cam02"]["psnr_matched"] > 100
    fit = res.summary["exposure_fit"]["cam01"]
    assert np.allclose(fit["gain"], 1.25, atol=0.05) and np.allclose(fit["bias"], 0.03, atol=0.02)
    assert all("_exposure_sums" not in r for r in res.rows)
