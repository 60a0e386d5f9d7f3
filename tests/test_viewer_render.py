"""GLSL splatting (headless, OSMesa forced) against an analytic Gaussian and against the
training rasterizer's torch reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from atgs.cameras import Camera, look_at
from atgs.gaussians import Gaussians
from atgs.headless_gl import create_headless_context
from scipy.spatial.transform import Rotation

from atgs.viewer.packing import pack_gaussians
from atgs.viewer.splat_renderer import RenderSettings, SplatRenderer


def _one_gaussian() -> Gaussians:
    return Gaussians(
        means=torch.tensor([[0.05, -0.03, 2.0]]),
        quats=torch.tensor([[0.9, 0.2, -0.3, 0.1]]),
        scales=torch.tensor([[0.1, 0.05, 0.02]]),
        opacities=torch.tensor([0.8]),
        colors=torch.tensor([[1.0, 0.5, 0.25]]),
    )


def _stored_quat(q: np.ndarray) -> np.ndarray:
    """The rotation as the vertex record stores it (docs/viewer.md): int16 of 32767 q / |q|."""
    return np.round(32767 * q / np.linalg.norm(q)) / 32767


def _analytic_alpha(g: Gaussians, cam: Camera, stored: bool = True) -> np.ndarray:
    """o exp(-0.5 d^T Sigma2d^-1 d) with Sigma2d = J W Sigma W^T J^T + 0.3 I, cut at 3 sigma
    and below 1/255, capped at 0.99 (numpy, float64, independent of the shader). ``stored``:
    with the 16-bit rotation of the vertex record (else the exact float quaternion)."""
    R, t = cam.R, cam.t
    m = R @ g.means[0].double().numpy() + t
    q = g.quats[0].double().numpy()
    q = _stored_quat(q) if stored else q
    Rg = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()  # scipy is scalar-last
    Sd = np.diag(g.scales[0].double().numpy() ** 2)
    S = R @ (Rg @ Sd @ Rg.T) @ R.T
    x, y, z = m
    fx, fy, cx, cy = cam.fx, cam.fy, cam.cx, cam.cy
    J = np.array([[fx / z, 0, -fx * x / z**2], [0, fy / z, -fy * y / z**2]])
    S2 = J @ S @ J.T + 0.3 * np.eye(2)
    u = np.array([fx * x / z + cx, fy * y / z + cy])
    px, py = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    d = np.stack([px - u[0], py - u[1]], -1)
    sig = 0.5 * np.einsum("hwi,ij,hwj->hw", d, np.linalg.inv(S2), d)
    a = np.minimum(0.99, float(g.opacities[0]) * np.exp(-sig))
    a[(a < 1 / 255) | (sig > 4.5)] = 0.0
    return a


def test_single_gaussian_is_the_analytic_ellipse(renderer: SplatRenderer) -> None:
    K = np.array([[50.0, 0, 30.3], [0, 55.0, 25.1], [0, 0, 1]])
    cam = Camera("c", 64, 48, K, np.eye(4))
    g = _one_gaussian()
    renderer.set_gaussians(pack_gaussians(g))
    ref = _analytic_alpha(g, cam)
    alpha = renderer.render_image(cam, RenderSettings(mode="alpha"))
    assert ref.sum() > 5.0  # the ellipse covers many pixels
    np.testing.assert_allclose(alpha, ref, atol=1e-5)
    bg = np.array([0.1, 0.2, 0.3])
    color = renderer.render_image(cam, RenderSettings(background=tuple(bg)))
    expect = ref[..., None] * np.array([1.0, 0.5, 0.25]) + (1 - ref[..., None]) * bg
    np.testing.assert_allclose(color, expect, atol=2e-5)
    depth = renderer.render_image(cam, RenderSettings(mode="depth"))
    np.testing.assert_allclose(depth, 2.0 * ref, atol=2e-5)
    # what the 16-bit rotation costs against the exact quaternion (docs/viewer.md: 1e-4)
    np.testing.assert_allclose(alpha, _analytic_alpha(g, cam, stored=False), atol=1e-4)


def test_large_gaussian_crossing_the_image_border(renderer: SplatRenderer) -> None:
    # A big, flat Gaussian near the top edge (taken from a trained model): its triangle reaches
    # far outside the viewport. llvmpipe's clipping of such triangles interpolated the
    # Gaussian's coordinates wrongly (alpha off by up to 27%) at some image sizes and not
    # others (here 120, 160, 200, 360, ... px wide), so every size from 120 to 680 px.
    g = Gaussians(
        means=torch.tensor([[-10.0887, 3.0167, 3.4435]]),
        quats=torch.tensor([[0.7075, 0.1404, 0.6753, -0.1540]]),
        scales=torch.tensor([[0.7825, 2.2431, 1e-9]]),
        opacities=torch.tensor([0.354]),
        colors=torch.tensor([[0.45, 0.3, 0.2]]),
    )
    w2c = np.array([[0.0, 1.0, 0.0, 0.0], [0.192012, 0.0, -0.981393, 0.588836],
                    [-0.981393, 0.0, -0.192012, 4.802424], [0.0, 0.0, 0.0, 1.0]])
    renderer.set_gaussians(pack_gaussians(g))
    for width in range(120, 700, 20):
        height = width * 3 // 4
        f = 213.027774 / 256 * width
        K = np.array([[f, 0, 0.5 * width], [0, f, 0.5 * height], [0, 0, 1]])
        cam = Camera("c", width, height, K, w2c)
        ref = _analytic_alpha(g, cam)
        assert ref[0].max() > 0.01 and ref.sum() > 0.01 * width * height  # crosses the top edge, big
        alpha = renderer.render_image(cam, RenderSettings(mode="alpha"))
        # float32 against float64 may round a pixel right at the cutoff either way
        at_cutoff = np.maximum(alpha, ref) < 1 / 255 + 2e-4
        assert at_cutoff[np.abs(alpha - ref) > 1e-5].sum() <= 3, f"{width}x{height}"
        np.testing.assert_allclose(alpha[~at_cutoff], ref[~at_cutoff], atol=1e-5, err_msg=f"{width}x{height}")


def test_rotated_camera_and_scale_modifier(renderer: SplatRenderer) -> None:
    # A camera that is not the identity: the shader must apply w2c like the numpy reference.
    w2c = look_at(np.array([0.7, -0.4, -1.5]), np.array([0.05, -0.03, 2.0]), np.array([0.0, -1.0, 0.2]))
    K = np.array([[70.0, 0, 40.0], [0, 70.0, 30.0], [0, 0, 1]])
    cam = Camera("c", 80, 60, K, w2c)
    g = _one_gaussian()
    renderer.set_gaussians(pack_gaussians(g))
    alpha = renderer.render_image(cam, RenderSettings(mode="alpha"))
    np.testing.assert_allclose(alpha, _analytic_alpha(g, cam), atol=1e-5)
    # scale modifier m renders exactly the Gaussians with scales * m
    alpha2 = renderer.render_image(cam, RenderSettings(mode="alpha", scale_modifier=0.5))
    g_half = Gaussians(g.means, g.quats, g.scales * 0.5, g.opacities, g.colors)
    np.testing.assert_allclose(alpha2, _analytic_alpha(g_half, cam), atol=1e-5)


def test_behind_camera_and_empty_give_background(renderer: SplatRenderer) -> None:
    cam = Camera("c", 32, 24, np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]]), np.eye(4))
    g = _one_gaussian()
    g.means[0, 2] = -2.0
    renderer.set_gaussians(pack_gaussians(g))
    img = renderer.render_image(cam, RenderSettings(background=(0.2, 0.4, 0.6)))
    np.testing.assert_allclose(img, np.broadcast_to([0.2, 0.4, 0.6], img.shape), atol=1e-6)
    empty = Gaussians(*(t[:0] for t in g.as_tuple()))
    renderer.set_gaussians(pack_gaussians(empty))
    assert renderer.render_image(cam, RenderSettings(mode="alpha")).max() == 0.0


def test_present_shows_the_target_in_each_mode(renderer: SplatRenderer) -> None:
    # The window's last pass, into an 8-bit framebuffer of the target's size (no filtering):
    # color = the target's rgb, alpha = gray coverage, depth = the colormap of z between the
    # nearest and farthest Gaussian (red near ... blue far), background where nothing is.
    import moderngl

    g, cam = _random_scene(400, seed=5)
    renderer.set_gaussians(pack_gaussians(g))
    ctx = renderer.ctx
    tex = ctx.texture((cam.width, cam.height), 3, dtype="f1")
    fbo = ctx.framebuffer([tex])
    shown = {}
    for mode in ("color", "alpha", "depth"):
        s = RenderSettings(mode=mode, background=(0.1, 0.2, 0.3))
        target = renderer.render_image(cam, s)
        renderer.present(fbo, (0, 0, cam.width, cam.height), s)
        raw = fbo.read(components=3)
        shown[mode] = np.frombuffer(raw, np.uint8).reshape(cam.height, cam.width, 3)[::-1] / 255.0
        if mode == "color":
            np.testing.assert_allclose(shown[mode], target, atol=1 / 255 + 1e-6)
        if mode == "alpha":
            np.testing.assert_allclose(shown[mode], np.repeat(target[..., None], 3, -1), atol=1 / 255 + 1e-6)
    alpha = renderer.render_image(cam, RenderSettings(mode="alpha"))
    empty, covered = alpha < 1e-4, alpha > 0.5
    assert empty.any() and covered.sum() > 20
    np.testing.assert_allclose(shown["depth"][empty], np.broadcast_to([0.1, 0.2, 0.3], shown["depth"][empty].shape), atol=1 / 255 + 1e-6)
    z = renderer.render_image(cam, RenderSettings(mode="depth"))[covered] / alpha[covered]
    near, far = z < np.quantile(z, 0.2), z > np.quantile(z, 0.8)
    rgb = shown["depth"][covered]
    # near is redder than far, far is bluer than near
    assert rgb[near, 0].mean() > rgb[far, 0].mean() + 0.2 and rgb[far, 2].mean() > rgb[near, 2].mean() + 0.2
    fbo.release()
    tex.release()
    del moderngl


def _random_scene(n: int, seed: int) -> tuple[Gaussians, Camera]:
    gen = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=gen) * torch.tensor([2.0, 1.5, 2.0]) - torch.tensor([1.0, 0.75, 1.0])
    g = Gaussians(
        means=means,
        quats=torch.randn(n, 4, generator=gen),
        scales=torch.exp(torch.rand(n, 3, generator=gen) * 1.5 - 4.0),
        opacities=torch.rand(n, generator=gen) * 0.9 + 0.05,
        colors=torch.rand(n, 3, generator=gen),
    )
    W, H = 96, 72
    K = np.array([[80.0, 0, 47.3], [0, 82.0, 35.6], [0, 0, 1]])
    cam = Camera("c", W, H, K, look_at(np.array([0.4, -0.5, -3.0]), np.zeros(3), np.array([0.0, -1.0, 0.0])))
    return g, cam


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return 10 * math.log10(1.0 / max(mse, 1e-20))


@pytest.mark.parametrize("exact_sort", [True, False])
def test_matches_training_rasterizer(renderer: SplatRenderer, exact_sort: bool) -> None:
    from atgs.render import rasterize_gaussians

    g, cam = _random_scene(400, seed=3)
    bg = (0.3, 0.1, 0.2)
    out = rasterize_gaussians(g, cam, background=torch.tensor(bg), backend="torch")
    renderer.set_gaussians(pack_gaussians(g))
    color = renderer.render_image(cam, RenderSettings(background=bg, exact_sort=exact_sort))
    alpha = renderer.render_image(cam, RenderSettings(mode="alpha", exact_sort=exact_sort))
    depth = renderer.render_image(cam, RenderSettings(mode="depth", exact_sort=exact_sort))
    ref_img = out.image.detach().numpy()
    assert float(out.alpha.mean()) > 0.2  # a scene with substance, not a blank comparison
    p = psnr(color, ref_img)
    assert p >= 35.0, f"PSNR GLSL vs rasterizer {p:.1f} dB"
    assert psnr(alpha, out.alpha.detach().numpy()) >= 35.0
    zmax = float(out.depth.max())
    assert psnr(depth / zmax, out.depth.detach().numpy() / zmax) >= 35.0


def test_matches_rasterizer_through_egl(renderer: SplatRenderer) -> None:
    from atgs.render import rasterize_gaussians

    ctx = create_headless_context("egl")
    r = SplatRenderer(ctx)
    try:
        g, cam = _random_scene(300, seed=5)
        out = rasterize_gaussians(g, cam, backend="torch")
        r.set_gaussians(pack_gaussians(g))
        assert psnr(r.render_image(cam), out.image.detach().numpy()) >= 35.0
    finally:
        r.release()
        ctx.release()
        # EGL and OSMesa share Mesa's GL dispatch: make the module's OSMesa context current
        # again, or the following tests would draw into no context.
        renderer.ctx.__enter__()


def _scene_with_close_gaussians() -> tuple[Gaussians, Camera]:
    """40 small Gaussians at view z 0.1-0.25 in front of 200 at z 1.5-2.5 (identity camera)."""
    gen = torch.Generator().manual_seed(7)
    z = torch.cat([0.1 + 0.15 * torch.rand(40, generator=gen), 1.5 + torch.rand(200, generator=gen)])
    xy = (torch.rand(240, 2, generator=gen) - 0.5) * torch.tensor([0.9, 0.7]) * z[:, None]
    n = len(z)
    g = Gaussians(means=torch.cat([xy, z[:, None]], 1), quats=torch.randn(n, 4, generator=gen),
                  scales=0.06 * z[:, None] * (0.5 + torch.rand(n, 3, generator=gen)),
                  opacities=0.3 + 0.6 * torch.rand(n, generator=gen), colors=torch.rand(n, 3, generator=gen))
    K = np.array([[80.0, 0, 48.0], [0, 80.0, 36.0], [0, 0, 1]])
    return g, Camera("c", 96, 72, K, np.eye(4))


def test_the_near_plane_is_the_rasterizers(renderer: SplatRenderer) -> None:
    """A model's near plane (0.3 here) culls the Gaussians between it and 0.01 in the player as
    in the rasterizer; the default near plane draws them (they change the image)."""
    from atgs.render import rasterize_gaussians

    g, cam = _scene_with_close_gaussians()
    r = SplatRenderer(renderer.ctx, near=0.3)
    try:
        r.set_gaussians(pack_gaussians(g))
        for exact in (True, False):
            img = r.render_image(cam, RenderSettings(exact_sort=exact))
            ref = rasterize_gaussians(g, cam, backend="torch", near=0.3).image.detach().numpy()
            assert psnr(img, ref) >= 35.0
            assert r.drawn_count() <= 200
        drawn_all = rasterize_gaussians(g, cam, backend="torch").image.detach().numpy()
        assert psnr(drawn_all, ref) < 25.0  # the close ones matter: the two near planes differ
        renderer.set_gaussians(pack_gaussians(g))
        assert psnr(renderer.render_image(cam, RenderSettings(exact_sort=True)), drawn_all) >= 35.0
    finally:
        r.release()


def test_constants_agree_with_rasterizer() -> None:
    import atgs.render.constants as rc
    import atgs.viewer.splat_renderer as vs

    for name in ("NEAR", "DILATION", "CLAMP_MARGIN", "RADIUS_SIGMAS", "ALPHA_MAX", "ALPHA_MIN"):
        assert getattr(vs, name) == getattr(rc, name), name


def test_large_gaussian_count_spans_texture_rows(renderer: SplatRenderer) -> None:
    # 2500 Gaussians use 3 texture rows (1024 per row): the last ones must still be fetched.
    n = 2500
    means = torch.zeros(n, 3)
    means[:, 2] = 5.0
    g = Gaussians(means, torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.full((n, 3), 1e-3),
                  torch.zeros(n), torch.zeros(n, 3))
    g.opacities[-1] = 0.9
    g.means[-1] = torch.tensor([0.025, 0.025, 2.0])  # projects onto pixel center (16.5, 16.5)
    g.scales[-1] = 0.2
    cam = Camera("c", 32, 32, np.array([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]]), np.eye(4))
    renderer.set_gaussians(pack_gaussians(g))
    a = renderer.render_image(cam, RenderSettings(mode="alpha"))
    assert a.max() == pytest.approx(0.9, abs=1e-4)  # the last Gaussian, and only it, is visible


def test_growing_frames_draw_from_the_new_buffers(renderer: SplatRenderer, monkeypatch) -> None:
    """A frame with more Gaussians than the buffers hold reallocates them; the draw must use the
    new ones. NVIDIA's driver hands a new buffer the GL name of the one just released (Mesa does
    not), so the GL names are made equal here: a VAO kept by name would draw the old buffers
    (it crashed the process on an H200)."""
    import moderngl

    monkeypatch.setattr(moderngl.Buffer, "glo", property(lambda self: 1))
    cam = Camera("c", 48, 40, np.array([[50.0, 0, 24], [0, 50.0, 20], [0, 0, 1]]), np.eye(4))

    def frame(n: int, seed: int) -> Gaussians:
        g = torch.Generator().manual_seed(seed)
        means = torch.rand(n, 3, generator=g) * torch.tensor([1.6, 1.4, 2.0]) - torch.tensor([0.8, 0.7, -2.0])
        return Gaussians(means, torch.randn(n, 4, generator=g), torch.rand(n, 3, generator=g) * 0.03 + 0.005,
                         torch.rand(n, generator=g) * 0.9, torch.rand(n, 3, generator=g))

    renderer.set_gaussians(pack_gaussians(frame(30, seed=0)))
    renderer.render_image(cam)
    big = frame(5000, seed=1)  # every column and the index buffer outgrow their first size
    renderer.set_gaussians(pack_gaussians(big))
    drawn = renderer.render_image(cam)
    fresh = SplatRenderer(renderer.ctx)
    try:
        fresh.set_gaussians(pack_gaussians(big))
        expected = fresh.render_image(cam)
    finally:
        fresh.release()
    assert float(np.abs(expected).max()) > 0.1, "the frame covers the image"
    np.testing.assert_array_equal(drawn, expected)


def test_radix_sort_agrees_with_exact_sort() -> None:
    from atgs.viewer.sorting import back_to_front, view_depths

    gen = np.random.default_rng(1)
    means = gen.normal(size=(5000, 3)).astype(np.float32) * 3
    w2c = look_at(np.array([0.0, -8.0, 1.0]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
    exact = back_to_front(means, w2c, 0.01, exact=True).numpy()
    fast = back_to_front(means, w2c, 0.01).numpy()
    z64 = means.astype(np.float64) @ w2c[2, :3] + w2c[2, 3]  # numpy reference of view_depths
    z = view_depths(torch.from_numpy(means), w2c).numpy()
    np.testing.assert_allclose(z, z64, rtol=1e-6, atol=1e-5)
    assert sorted(exact.tolist()) == sorted(fast.tolist()) == np.flatnonzero(z > 0.01).tolist()
    assert np.all(np.diff(z[exact]) <= 0)  # the reference: strictly far to near
    quantum = (z[exact].max() - z[exact].min()) / 65535
    assert np.all(np.diff(z[fast]) <= 1.01 * quantum)  # out of order by at most one 16-bit step


def test_frustum_cull_is_conservative_and_culls(renderer: SplatRenderer) -> None:
    # Gaussians all around the camera, many off-screen or behind, some large and elongated,
    # some just outside the borders: culled drawing must equal drawing everything.
    from atgs.viewer.sorting import FrustumCull, back_to_front
    from atgs.viewer.splat_renderer import clamp_limits

    gen = torch.Generator().manual_seed(7)
    n = 3000
    g = Gaussians(
        means=(torch.rand(n, 3, generator=gen) * 2 - 1) * torch.tensor([6.0, 6.0, 4.0]) + torch.tensor([0, 0, 3.0]),
        quats=torch.randn(n, 4, generator=gen),
        scales=torch.exp(torch.randn(n, 3, generator=gen) * 1.2 - 2.5),
        opacities=torch.rand(n, generator=gen) * 0.9 + 0.1,
        colors=torch.rand(n, 3, generator=gen),
    )
    K = np.array([[60.0, 0, 31.0], [0, 60.0, 25.0], [0, 0, 1]])
    cam = Camera("c", 64, 48, K, np.eye(4))
    packed = pack_gaussians(g)
    cull = FrustumCull(K, 64, 48, clamp_limits(K, 64, 48))
    kept = back_to_front(packed.means, cam.w2c, 0.01, extent=packed.extent, cull=cull).numpy()
    front = back_to_front(packed.means, cam.w2c, 0.01).numpy()
    assert len(kept) < 0.6 * len(front)  # the cull does remove work
    renderer.set_gaussians(packed)
    culled = renderer.render_image(cam, RenderSettings(background=(0.1, 0.2, 0.3), exact_sort=True))
    # reference: the same draw with the cull disabled (every Gaussian in front of the camera)
    packed_nocull = pack_gaussians(g)
    packed_nocull.extent = torch.full((n,), 1e9)  # huge bound: nothing can be culled
    renderer.set_gaussians(packed_nocull)
    full = renderer.render_image(cam, RenderSettings(background=(0.1, 0.2, 0.3), exact_sort=True))
    assert renderer.timings.drawn == len(front)
    np.testing.assert_allclose(culled, full, atol=1e-6)
