"""Anchor initialization helpers against brute force."""

import torch

from atgs.model.anchors import knn_mean_sq_dist


def brute_knn(q: torch.Tensor, r: torch.Tensor, k: int, drop_self: bool) -> torch.Tensor:
    out = []
    for i, x in enumerate(q):
        d = sorted(float(((x - y) ** 2).sum()) for j, y in enumerate(r) if not (drop_self and j == i))
        out.append(sum(d[:k]) / len(d[:k]))
    return torch.tensor(out)


def test_knn_mean_sq_dist_matches_brute_force():
    line = torch.tensor([[float(i), 0.0, 0.0] for i in range(5)])
    assert torch.allclose(knn_mean_sq_dist(line, line, 3), torch.tensor([14 / 3, 2, 2, 2, 14 / 3]))
    pts = torch.randn(40, 3, generator=torch.Generator().manual_seed(0))
    for k in (1, 3):
        for self_ in (True, False):
            got = knn_mean_sq_dist(pts, pts, k, exclude_self=self_, chunk=7)
            assert torch.allclose(got, brute_knn(pts, pts, k, self_).float(), rtol=1e-5), (k, self_)
