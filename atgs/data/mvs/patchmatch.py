"""Depth of one reference camera by PatchMatch stereo with slanted planes (torch, vectorized, CPU).

Every pixel holds a plane (inverse depth along its ray and a normal facing the camera). Its
cost is 1 - NCC between the reference window and the source image sampled where the window's
pixels, lifted onto that plane, project: a slanted window, so ground planes and walls seen at
grazing angles match as well as surfaces facing the camera (a fronto-parallel plane sweep fails
there). Costs are averaged over the best ``top_k`` sources (default 1: the best source alone).

Red-black PatchMatch (Galliani et al. 2015, "Gipuma"): the pixels of one checkerboard colour try
the planes of their cheapest neighbours of the other colour at distances 1 and 3, then random
perturbations of their own plane, and keep the cheapest; then the other colour. Iterations run on
a pyramid from random planes at the coarsest level, then at the working resolution; a second
pass (:func:`refine_geometric`) adds the disagreement with the sources' first-pass depth maps.

``patchmatch_cost_reference`` evaluates the same cost one pixel, source and window sample at a
time with NumPy; the tests compare the fast path with it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from atgs.data.mvs.config import StereoConfig
from atgs.data.mvs.views import View

INVALID_COST = 2.0  # 1 - NCC lies in [0, 2]; a source that cannot see the point scores the worst
NCC_EPS = 1e-3  # added to window standard deviations (intensities in [0,1]): flat windows correlate 0


@dataclass
class DepthMap:
    """Per-pixel depth (OpenCV z, 0 = none) and confidence (mean NCC of the best sources, 0 = none)."""

    depth: torch.Tensor  # (H,W) float32
    confidence: torch.Tensor  # (H,W) float32
    plane_depth: torch.Tensor | None = None  # (H,W) the planes' depth everywhere (unfiltered)
    normal: torch.Tensor | None = None  # (H,W,3) the planes' camera-space normals

# Neighbours whose planes a pixel tries: the other checkerboard colour at distances 1 and 3.
PROPAGATION = ((0, -1), (0, 1), (-1, 0), (1, 0), (0, -3), (0, 3), (-3, 0), (3, 0))
MAX_TILT_DEG = 88.0  # random normals: at most this far from facing the camera head-on
MIN_LEVEL_SIDE = 32  # the coarsest level keeps at least this many pixels on its short side


def window_offsets(window: int, step: int) -> torch.Tensor:
    """(Q,2) integer offsets (dx, dy) of the window samples: every ``step``-th pixel of a square of
    side at most ``window``, symmetric about the center, which is always one of them (5, 2: the
    offsets -2, 0, 2 in x and y, 9 samples)."""
    r = (window // 2) // step * step
    o = torch.arange(-r, r + 1, step)
    dy, dx = torch.meshgrid(o, o, indexing="ij")
    return torch.stack([dx.reshape(-1), dy.reshape(-1)], 1)


class PlaneCost:
    """Matching cost of plane hypotheses at reference pixels against a set of source views.

    A plane n . X = c (reference camera coordinates) maps reference pixels to source pixels by
    the homography H = K_s (R + t n^T / c) K_r^-1 = G + e m^T, with m = K_r^-T n / c. The window
    samples p + o of a pixel p are then h_p + H[:, :2] o: one small per-pixel matrix, applied to
    the fixed offsets. Float32; the reference windows are normalized once. The reference image
    is replicate-padded: window samples past its border take the border pixel's value.
    """

    def __init__(self, ref: View, srcs: Sequence[View], cfg: StereoConfig,
                 src_depths: Sequence[torch.Tensor] | None = None) -> None:
        self.top_k = cfg.top_k
        self.geo_weight, self.geo_max = cfg.geo_weight, cfg.geo_max_px
        self.h, self.w = h, w = ref.gray.shape
        self.off = window_offsets(cfg.window, cfg.window_step)
        self.offf = self.off.float()
        self.center = int(((self.off == 0).all(1)).nonzero()[0])
        idx = torch.arange(h * w)
        x, y = idx % w, torch.div(idx, w, rounding_mode="floor")
        xq = (x[:, None] + self.off[:, 0]).clamp(0, w - 1)
        yq = (y[:, None] + self.off[:, 1]).clamp(0, h - 1)
        rw = ref.gray.reshape(-1)[yq * w + xq]  # (HW,Q)
        self.ref_std = rw.std(1, unbiased=False)
        self.ref_norm = (rw - rw.mean(1, keepdim=True)) / (self.ref_std[:, None] + NCC_EPS)
        self.kinv = torch.from_numpy(np.linalg.inv(ref.cam.K)).float()
        self.pix = torch.stack([x.float() + 0.5, y.float() + 0.5, torch.ones(h * w)], -1)  # (HW,3)
        self.ray = self.pix @ self.kinv.T  # (HW,3) rays through the pixel centers
        T = [s.cam.w2c @ np.linalg.inv(ref.cam.w2c) for s in srcs]
        kinv = np.linalg.inv(ref.cam.K)
        self.G = torch.from_numpy(np.stack([s.cam.K @ t[:3, :3] @ kinv for s, t in zip(srcs, T)])).float()  # (N,3,3)
        self.e = torch.from_numpy(np.stack([s.cam.K @ t[:3, 3] for s, t in zip(srcs, T)])).float()  # (N,3)
        # homogeneous pixels -> grid_sample's [-1, 1] (pixel centers at +0.5, align_corners=False)
        self.to_grid = torch.stack([torch.tensor([[2.0 / s.cam.width, 0, 0], [0, 2.0 / s.cam.height, 0],
                                                  [-1.0, -1.0, 1.0]]) for s in srcs])[:, None]  # (N,1,3,3)
        self.basis_t = torch.cat([torch.ones(len(self.off), 1), self.offf], 1)  # (Q,3): [1, ox, oy]
        sizes = {(s.cam.height, s.cam.width) for s in srcs}
        self.batch = torch.stack([s.gray for s in srcs])[:, None] if len(sizes) == 1 else None
        self.images = [s.gray[None, None] for s in srcs]
        # geometric consistency with the sources' depth maps: source pixel -> source ray -> reference pixel
        self.src_depths = None if src_depths is None else [d.float()[None, None] for d in src_depths]
        back = [np.linalg.inv(t) for t in T]
        self.src_kinv = torch.from_numpy(np.stack([np.linalg.inv(s.cam.K) for s in srcs])).float()  # (N,3,3)
        self.back_A = torch.from_numpy(np.stack([ref.cam.K @ b[:3, :3] for b in back])).float()  # (N,3,3)
        self.back_b = torch.from_numpy(np.stack([ref.cam.K @ b[:3, 3] for b in back])).float()  # (N,3)
        self.src_size = torch.tensor([[s.cam.width, s.cam.height] for s in srcs], dtype=torch.float32)

    def __call__(self, idx: torch.Tensor, inv: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
        """Aggregated cost (M,) of the planes (inverse depth along the pixel ray, camera-space
        normal) at reference pixels ``idx`` (M,), row-major."""
        inv, normal = inv.float(), normal.float()
        c = (normal * self.ray[idx]).sum(-1) / inv.clamp_min(1e-12)  # plane: n . X = c
        m = (normal @ self.kinv) / c[:, None]  # (M,3); m . [u, v, 1] = 1 / depth on the plane
        front = (inv[:, None] + m[:, :2] @ self.offf.T > 0).all(1)  # the whole window in front
        # source homogeneous coordinates of the window samples, [1, ox, oy] @ C per source and
        # pixel, with C's rows h_p, H[:, 0], H[:, 1]; the columns x, y are pre-scaled so that
        # x / z is grid_sample's coordinate in [-1, 1] (x' = 2x / width - z)
        hp = torch.einsum("nij,mj->nmi", self.G, self.pix[idx]) + self.e[:, None] * inv[None, :, None]
        hx = self.G[:, None, :, 0] + self.e[:, None] * m[None, :, 0:1]
        hy = self.G[:, None, :, 1] + self.e[:, None] * m[None, :, 1:2]
        C = torch.stack([hp, hx, hy], 1) @ self.to_grid  # (N,3,M,3)
        n_src, _, n_pix, _ = C.shape
        h = (self.basis_t @ C.reshape(n_src, 3, -1)).reshape(n_src, -1, n_pix, 3)  # (N,Q,M,3)
        z = h[..., 2]
        grid = h[..., :2] / z.clamp_min(1e-9)[..., None]  # (N,Q,M,2)
        gc = grid[:, self.center]  # the window center must be in front of the source and inside its image
        seen = front[None] & (z[:, self.center] > 1e-9) & (gc.abs().amax(-1) <= 1)
        if self.batch is not None:
            S = F.grid_sample(self.batch, grid, mode="bilinear", padding_mode="border", align_corners=False)[:, 0]
        else:
            S = torch.cat([F.grid_sample(im, g[None], mode="bilinear", padding_mode="border", align_corners=False)[0]
                           for im, g in zip(self.images, grid)])
        S = S - S.mean(1, keepdim=True)  # S: (N,Q,M)
        sd = S.square().mean(1).sqrt()
        cross = (S * self.ref_norm[idx].T[None]).mean(1)
        ncc = (cross / (sd + NCC_EPS)).clamp(-1, 1)
        cost = torch.where(seen, 1.0 - ncc, INVALID_COST)
        if self.src_depths is not None:
            cost = cost + self.geo_weight * self._reprojection(idx, gc).clamp(max=self.geo_max)
        k = min(self.top_k, cost.shape[0])
        if k == 1:
            return cost.amin(0)
        return cost.topk(k, dim=0, largest=False).values.mean(0) if k < cost.shape[0] else cost.mean(0)


    def _reprojection(self, idx: torch.Tensor, gc: torch.Tensor) -> torch.Tensor:
        """(N,M) pixel distance between each reference pixel and where its hypothesis point comes
        back to after a round trip through each source's depth map (inf where it has none)."""
        uv = (gc + 1) * self.src_size[:, None] / 2  # source pixel coordinates of the window centers
        if self.batch is not None:
            d = F.grid_sample(torch.cat(self.src_depths), gc[:, :, None], mode="nearest", padding_mode="border",
                              align_corners=False)[:, 0, :, 0]
        else:
            d = torch.cat([F.grid_sample(dm, g[None, :, None], mode="nearest", padding_mode="border",
                                         align_corners=False)[0, :, :, 0] for dm, g in zip(self.src_depths, gc)])
        ph = torch.cat([uv, torch.ones_like(uv[..., :1])], -1)  # (N,M,3)
        Xs = torch.einsum("nij,nmj->nmi", self.src_kinv, ph) * d[..., None]
        back = torch.einsum("nij,nmj->nmi", self.back_A, Xs) + self.back_b[:, None]
        pr = back[..., :2] / back[..., 2:].clamp_min(1e-9)
        err = (pr - self.pix[idx][None, :, :2]).norm(dim=-1)
        return torch.where((d > 0) & (back[..., 2] > 0), err, torch.full_like(err, float("inf")))


def _face_camera(normal: torch.Tensor, ray: torch.Tensor) -> torch.Tensor:
    normal = normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return torch.where(((normal * ray).sum(-1) > 0)[:, None], -normal, normal)


def random_normals(ray: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Random unit normals facing the camera, tilted at most MAX_TILT_DEG from the ray."""
    d = -ray / ray.norm(dim=-1, keepdim=True)
    tilt = torch.rand(ray.shape[0], generator=gen) * np.radians(MAX_TILT_DEG)
    a = torch.randn(ray.shape, generator=gen)
    a = a - (a * d).sum(-1, keepdim=True) * d  # a direction perpendicular to the ray
    a = a / a.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return d * torch.cos(tilt)[:, None] + a * torch.sin(tilt)[:, None]


def _transfer(ray: torch.Tensor, src_idx: torch.Tensor, dst_idx: torch.Tensor, inv: torch.Tensor,
              normal: torch.Tensor) -> torch.Tensor:
    """Inverse depth at pixels ``dst_idx`` of the planes held by pixels ``src_idx`` (0: behind)."""
    n = normal[src_idx]
    c = (n * ray[src_idx]).sum(-1) / inv[src_idx].clamp_min(1e-12)
    return ((n * ray[dst_idx]).sum(-1) / c).clamp_min(0)  # 1/t with t = c / (n . r)


def _iterate(cost: PlaneCost, inv: torch.Tensor, normal: torch.Tensor, best: torch.Tensor, lo: float, hi: float,
             iterations: int, candidates: int, gen: torch.Generator, scale0: float = 1.0, random: bool = True) -> None:
    """Red-black PatchMatch iterations, in place on (inv, normal, best) of all pixels. Each pixel
    tries the planes of its ``candidates`` cheapest propagation neighbours (Xu and Tao 2019,
    "ACMM": the neighbours' own costs choose which planes are worth a test), then one random
    perturbation of its plane and, in the first iteration (if ``random``), one random plane."""
    h, w = cost.h, cost.w
    ys, xs = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    colour = ((xs + ys) % 2).reshape(-1)
    off = torch.tensor(PROPAGATION)
    for it in range(iterations):
        scale = scale0 * 0.5 ** it  # perturbations shrink as the planes settle
        for c in (0, 1):
            idx = torch.nonzero(colour == c).reshape(-1)
            x, y = idx % w, torch.div(idx, w, rounding_mode="floor")
            q = (y[:, None] + off[:, 1]).clamp(0, h - 1) * w + (x[:, None] + off[:, 0]).clamp(0, w - 1)  # (M,8)
            pick = best[q].topk(min(candidates, q.shape[1]), dim=1, largest=False).indices
            for k in range(pick.shape[1]):
                qk = q.gather(1, pick[:, k:k + 1])[:, 0]
                _keep_best(cost, idx, _transfer(cost.ray, qk, idx, inv, normal), normal[qk], inv, normal, best, lo, hi)
            ray = cost.ray[idx]
            pert_inv = inv[idx] + (hi - lo) * 0.1 * scale * (2 * torch.rand(idx.shape[0], generator=gen) - 1)
            pert_n = _face_camera(normal[idx] + 0.3 * scale * torch.randn(idx.shape[0], 3, generator=gen), ray)
            _keep_best(cost, idx, pert_inv, pert_n, inv, normal, best, lo, hi)
            if it == 0 and random:
                rand_inv = lo + (hi - lo) * torch.rand(idx.shape[0], generator=gen)
                _keep_best(cost, idx, rand_inv, random_normals(ray, gen), inv, normal, best, lo, hi)


def _keep_best(cost: PlaneCost, idx: torch.Tensor, cand_inv: torch.Tensor, cand_n: torch.Tensor,
               inv: torch.Tensor, normal: torch.Tensor, best: torch.Tensor, lo: float, hi: float) -> None:
    inside = (cand_inv >= lo) & (cand_inv <= hi)
    c = torch.where(inside, cost(idx, cand_inv.clamp(lo, hi), cand_n), torch.full_like(cand_inv, INVALID_COST))
    better = c < best[idx]
    sel = idx[better]
    inv[sel], normal[sel], best[sel] = cand_inv[better], cand_n[better], c[better]


def _scaled(view: View, factor: float) -> View:
    cam = view.cam.scaled(factor)
    g = F.interpolate(view.gray[None, None], size=(cam.height, cam.width), mode="area")[0, 0]
    return View(cam, g, view.rgb)


def patchmatch(ref: View, srcs: Sequence[View], near: float, far: float, cfg: StereoConfig,
               seed: int = 0) -> DepthMap:
    """Depth and confidence of ``ref`` from its source views (fast path). Coarse levels (each half
    the size of the next, down to MIN_LEVEL_SIDE pixels) run ``coarse_iterations`` each from
    random planes; the working resolution then runs ``iterations``."""
    h, w = ref.gray.shape
    if not srcs:
        z = torch.zeros(h, w)
        return DepthMap(z, z.clone())
    gen = torch.Generator().manual_seed(seed)
    lo, hi = 1.0 / far, 1.0 / near
    factors = [1.0]
    while len(factors) < cfg.levels and min(h, w) * factors[-1] / 2 >= MIN_LEVEL_SIDE:
        factors.append(factors[-1] / 2)
    inv = normal = None
    prev = (0, 0)  # the previous level's (h, w), set at the end of each level
    for li, f in enumerate(reversed(factors)):
        views = (ref, list(srcs)) if f == 1.0 else (_scaled(ref, f), [_scaled(s, f) for s in srcs])
        pc = PlaneCost(*views, cfg)
        n = pc.h * pc.w
        idx = torch.arange(n)
        if inv is None:
            inv = lo + (hi - lo) * torch.rand(n, generator=gen)
            normal = random_normals(pc.ray, gen)
        else:  # upsample the previous level's planes: bilinear inverse depth, nearest normal
            inv = F.interpolate(inv.view(1, 1, *prev), size=(pc.h, pc.w), mode="bilinear", align_corners=False).reshape(-1)
            normal = F.interpolate(normal.T.reshape(1, 3, *prev), size=(pc.h, pc.w), mode="nearest").reshape(3, -1).T
            normal = _face_camera(normal.contiguous(), pc.ray)
        best = pc(idx, inv, normal)
        its = cfg.iterations if f == 1.0 else cfg.coarse_iterations
        _iterate(pc, inv, normal, best, lo, hi, its, cfg.candidates, gen, scale0=1.0 if li == 0 else 0.25)
        prev = (pc.h, pc.w)
    return _result(pc, inv, normal, best, cfg)


def refine_geometric(ref: View, srcs: Sequence[View], src_depths: Sequence[torch.Tensor], start: DepthMap,
                     near: float, far: float, cfg: StereoConfig, seed: int = 0) -> DepthMap:
    """More PatchMatch iterations at the working resolution, from ``start``'s planes, with each
    source's cost raised by ``geo_weight`` x the round-trip reprojection error through that
    source's depth map (truncated at ``geo_max_px``): where the images alone are ambiguous, the
    plane that the other cameras' depths agree with wins (Xu and Tao 2019, "ACMM")."""
    h, w = ref.gray.shape
    if not srcs or start.normal is None or cfg.geo_iterations <= 0:
        return start
    gen = torch.Generator().manual_seed(seed + 7919)
    lo, hi = 1.0 / far, 1.0 / near
    pc = PlaneCost(ref, srcs, cfg, src_depths)
    idx = torch.arange(h * w)
    d = start.plane_depth.reshape(-1)
    inv = torch.where(d > 0, 1.0 / d.clamp_min(1e-12), torch.full_like(d, (lo + hi) / 2))
    normal = start.normal.reshape(-1, 3).clone()
    best = pc(idx, inv, normal)
    _iterate(pc, inv, normal, best, lo, hi, cfg.geo_iterations, cfg.candidates, gen, scale0=0.25, random=False)
    photometric = PlaneCost(ref, srcs, cfg)  # the confidence is the images' agreement alone
    return _result(photometric, inv, normal, photometric(idx, inv, normal), cfg)


def _result(pc: PlaneCost, inv: torch.Tensor, normal: torch.Tensor, best: torch.Tensor, cfg: StereoConfig) -> DepthMap:
    h, w = pc.h, pc.w
    ncc = (1.0 - best).reshape(h, w)
    plane_depth = 1.0 / inv.reshape(h, w).clamp_min(1e-12)
    ok = (ncc >= cfg.min_ncc) & (pc.ref_std.reshape(h, w) >= cfg.min_texture) & (inv.reshape(h, w) > 0)
    depth = torch.where(ok, plane_depth, torch.zeros(h, w))
    return DepthMap(depth.float(), torch.where(ok, ncc, torch.zeros_like(ncc)).float(),
                    plane_depth.float(), normal.reshape(h, w, 3).float())


def patchmatch_cost_reference(ref: View, srcs: Sequence[View], pixel: tuple[int, int], inv: float,
                              normal: np.ndarray, window: int, step: int, top_k: int) -> float:
    """The cost of one plane at one pixel, one source and window sample at a time (NumPy)."""
    x, y = pixel
    Kinv = np.linalg.inv(ref.cam.K)
    rp = Kinv @ np.array([x + 0.5, y + 0.5, 1.0])
    n = np.asarray(normal, np.float64)
    c = n @ rp / inv
    R = ref.gray.numpy().astype(np.float64)
    offs = window_offsets(window, step).numpy()
    rw, pts = [], []
    for dx, dy in offs:
        xq, yq = min(max(x + dx, 0), ref.cam.width - 1), min(max(y + dy, 0), ref.cam.height - 1)
        rq = Kinv @ np.array([xq + 0.5, yq + 0.5, 1.0])
        t = c / (n @ rq)
        if t <= 0:
            return INVALID_COST
        rw.append(R[yq, xq])
        pts.append(np.linalg.inv(ref.cam.w2c) @ np.append(rq * t, 1.0))  # world point on the plane
    rw = np.array(rw)
    costs = []
    for src in srcs:
        S = src.gray.numpy().astype(np.float64)
        sw = []
        seen = False
        for (dx, dy), X in zip(offs, pts):
            uv, z = src.cam.project(X[None, :3])
            sw.append(_bilinear_border(S, uv[0, 0], uv[0, 1]))
            if dx == 0 and dy == 0:
                seen = z[0] > 0 and 0 <= uv[0, 0] <= src.cam.width and 0 <= uv[0, 1] <= src.cam.height
        sw = np.array(sw)
        ncc = np.mean((rw - rw.mean()) / (rw.std() + NCC_EPS) * (sw - sw.mean())) / (sw.std() + NCC_EPS)
        costs.append(1.0 - np.clip(ncc, -1, 1) if seen else INVALID_COST)
    return float(np.mean(sorted(costs)[:top_k]))


def _bilinear_border(img: np.ndarray, x: float, y: float) -> float:
    """Bilinear sample at continuous pixel coordinates (pixel centers at +0.5), clamped to the border."""
    h, w = img.shape
    fx, fy = min(max(x - 0.5, 0.0), w - 1.0), min(max(y - 0.5, 0.0), h - 1.0)
    x0, y0 = int(np.floor(fx)), int(np.floor(fy))
    x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
    ax, ay = fx - x0, fy - y0
    return float((img[y0, x0] * (1 - ax) + img[y0, x1] * ax) * (1 - ay) + (img[y1, x0] * (1 - ax) + img[y1, x1] * ax) * ay)
