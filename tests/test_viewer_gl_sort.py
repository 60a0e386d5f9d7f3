"""The depth sort and cull in GL compute shaders (atgs/viewer/gl_sort.py) against the torch sort
(atgs/viewer/sorting.py) on the same inputs: the same visible set and count, keys within one
level of torch's (the float32 key scale) and a stable sort of them, plus the edge cases, the
indirect draw, and the dispatch split over y for very large counts."""

from __future__ import annotations

import types

import moderngl
import numpy as np
import pytest
import torch

from atgs.cameras import look_at
from atgs.viewer import gl_sort
from atgs.viewer.gl_sort import GLDepthSort, GLSortUnavailable, min_stored_opacity
from atgs.viewer.packing import row_norms
from atgs.viewer.sorting import FrustumCull, _affine_rows, _cull_planes, back_to_front
from atgs.viewer.splat_renderer import clamp_limits

NEAR = 0.01
W, H = 64, 48
K = np.array([[60.0, 0, 31.0], [0, 58.0, 25.0], [0, 0, 1]])
W2C = look_at(np.array([0.5, -7.0, 1.5]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
CULL = FrustumCull(K, W, H, clamp_limits(K, W, H))


@pytest.fixture(scope="module")
def ctx(compute_ctx):
    return compute_ctx  # (tests/conftest.py: fails, not skips, without OpenGL 4.3)


@pytest.fixture(scope="module", params=[gl_sort.BLOCK_SIZE, 100], ids=lambda b: f"block{b}")
def sorter(ctx, request):
    """The default block size and one that divides none of the counts."""
    s = GLDepthSort(ctx, block_size=request.param)
    yield s
    s.release()


def _scene(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Means, scales and 16-bit opacities like test_viewer_sorting's scene: some Gaussians
    behind the camera, many off-screen, some fainter than the alpha cutoffs."""
    gen = np.random.default_rng(seed)
    means = (gen.uniform(-1, 1, (n, 3)) * [14.0, 8.0, 8.0]).astype(np.float32)
    scales = np.exp(gen.normal(-2.6, 1.2, (n, 3))).astype(np.float32)
    opacity16 = np.round(65535 * gen.uniform(0, 1, n)).astype(np.uint16)
    return means, scales, opacity16


def _buffers(ctx, means: np.ndarray, scales: np.ndarray, opacity16: np.ndarray) -> list[moderngl.Buffer]:
    """The packing layout: means and scales float32 x3, opacity_rgb uint16 x4 (opacity first)."""
    opacity_rgb = np.zeros((len(opacity16), 4), dtype=np.uint16)
    opacity_rgb[:, 0] = opacity16
    opacity_rgb[:, 1:] = 12345  # colour bits must not leak into the opacity
    return [ctx.buffer(a.tobytes()) if a.size else ctx.buffer(reserve=16) for a in (means, scales, opacity_rgb)]


def _torch(means, scales, opacity16, w2c, cull, min_alpha, near=NEAR):
    """torch's order on the same (quantized) inputs, and its keys and unfloored key levels
    recomputed in numpy the way sorting._back_to_front computes them (checked against its order)."""
    n = len(means)
    opacity = opacity16.astype(np.float32) / np.float32(65535)
    extent = row_norms(torch.from_numpy(scales)).view(-1)
    order = back_to_front(torch.from_numpy(means), w2c, near, extent=extent, cull=cull,
                          opacity=torch.from_numpy(opacity), min_alpha=min_alpha).numpy()
    w = np.asarray(w2c, dtype=np.float64)
    A, b = w[2:3, :3], w[2, 3:]
    if cull is not None:
        normals, offsets, _ = _cull_planes(w, cull)
        A, b = np.concatenate([A, normals]), np.concatenate([b, offsets])
    z = _affine_rows(torch.from_numpy(means), A, b)[0].numpy() if n else np.zeros(0, np.float32)
    keys, level = np.full(n, 65535, dtype=np.int64), np.zeros(n, dtype=np.float32)
    if len(order):
        zmin, zmax = float(z[order].min()), float(z[order].max())
        scale = 65534 / (zmax - zmin) if zmax > zmin else 0.0
        level[order] = (np.float32(zmax) - z[order]) * np.float32(scale)
        keys[order] = np.floor(np.clip(level[order], 0, 65534))
    assert np.array_equal(np.argsort(keys, kind="stable")[: len(order)], order), "the emulation is not torch's"
    return order, keys, level, z


def _check_equal_to_torch(sorter, ctx, means, scales, opacity16, w2c=W2C, cull=CULL, min_alpha=1 / 255, near=NEAR):
    bufs = _buffers(ctx, means, scales, opacity16)
    got = sorter.sort(*bufs, len(means), w2c, near, cull, min_alpha)
    order, keys, level, z = _torch(means, scales, opacity16, w2c, cull, min_alpha, near)
    drawn = got.drawn()
    assert drawn == len(order)
    gl_keys = got.keys().astype(np.int64)
    assert np.array_equal(gl_keys == 65535, keys == 65535), "the visible sets differ"
    indices = got.indices()
    assert np.array_equal(indices, np.argsort(gl_keys, kind="stable")[:drawn]), "not a stable sort of the keys"
    differ = np.flatnonzero(gl_keys != keys)
    assert np.abs(gl_keys - keys).max(initial=0) <= 1
    assert len(differ) <= 0.01 * max(drawn, 1)
    # a key may differ only where torch's unfloored level sits at a floor boundary
    assert np.all(np.abs(level[differ] - np.round(level[differ])) < 0.02)
    if len(differ) == 0:
        assert np.array_equal(indices, order)
    if drawn:
        zmin, zmax = got.depth_range()
        assert zmin == pytest.approx(float(z[order].min()), rel=1e-6, abs=1e-7)
        assert zmax == pytest.approx(float(z[order].max()), rel=1e-6, abs=1e-7)
    for b in bufs:
        b.release()
    return got, order, differ


@pytest.mark.parametrize("n", [1000, 4099, 60_000])
@pytest.mark.parametrize("cull", [None, CULL], ids=["no-cull", "cull"])
@pytest.mark.parametrize("min_alpha", [0.0, 1 / 255, 0.3])
def test_equals_the_torch_sort(sorter, ctx, n, cull, min_alpha) -> None:
    means, scales, opacity16 = _scene(n, seed=n)
    _, order, _ = _check_equal_to_torch(sorter, ctx, means, scales, opacity16, cull=cull, min_alpha=min_alpha)
    assert 0.05 * n < len(order) < (0.98 if cull is None else 0.6) * n  # culled and visible ones both occur


@pytest.mark.parametrize("cull", [None, CULL], ids=["no-cull", "cull"])
def test_a_model_near_plane_culls_as_the_torch_sort(sorter, ctx, cull) -> None:
    """A model's near plane (2.0 scene units here) culls the same Gaussians on the GL as in torch."""
    means, scales, opacity16 = _scene(4000, seed=11)
    _, order, _ = _check_equal_to_torch(sorter, ctx, means, scales, opacity16, cull=cull, near=2.0)
    _, order_default, _ = _check_equal_to_torch(sorter, ctx, means, scales, opacity16, cull=cull)
    assert 0 < len(order) < len(order_default)  # some Gaussians lie between 0.01 and 2.0


def test_keys_differ_only_rarely(sorter, ctx) -> None:
    """Over a large scene the float32 key scale moves few keys (and then by one level)."""
    means, scales, opacity16 = _scene(200_000, seed=7)
    for cull in (None, CULL):
        _, order, differ = _check_equal_to_torch(sorter, ctx, means, scales, opacity16, cull=cull)
        assert len(differ) <= 0.005 * len(order)


def test_equal_depths_keep_index_order(sorter, ctx) -> None:
    """Many exactly equal depths (a camera looking along +z: z is the mean's z): the sort is
    stable, ties stay in index order, as torch's stable sort keeps them; and deterministic."""
    gen = np.random.default_rng(3)
    n = 20_000
    means = np.stack([gen.uniform(-1, 1, n), gen.uniform(-1, 1, n),
                      gen.choice(np.float32([2.0, 3.0, 3.5, 5.0]), n)], 1).astype(np.float32)
    means[::7, 2] = gen.uniform(1.0, 6.0, len(means[::7])).astype(np.float32)
    scales = np.full((n, 3), 0.01, dtype=np.float32)
    opacity16 = np.full(n, 40000, dtype=np.uint16)
    w2c = np.eye(4)
    got, order, differ = _check_equal_to_torch(sorter, ctx, means, scales, opacity16, w2c=w2c, cull=None)
    assert len(order) == n and np.all(differ % 7 == 0)  # only the scattered depths may sit at a floor boundary
    first = got.indices().copy()
    again = _check_equal_to_torch(sorter, ctx, means, scales, opacity16, w2c=w2c, cull=None)[0].indices()
    assert np.array_equal(first, again)
    ties = order[means[order, 2] == 3.0]
    assert len(ties) > 1000 and np.all(np.diff(ties) > 0)


def _command(order) -> tuple[int, ...]:
    return tuple(int(v) for v in np.frombuffer(order.indirect_buffer.read(20), dtype=np.uint32))


def test_no_gaussians_one_gaussian_and_none_visible(sorter, ctx) -> None:
    empty = sorter.sort(*_buffers(ctx, *_scene(0, 0)), 0, W2C, NEAR, CULL, 1 / 255)
    assert empty.drawn() == 0 and len(empty.indices()) == 0 and len(empty.keys()) == 0
    assert _command(empty) == (0, 1, 0, 0, 0) and empty.depth_range() == (0.0, 0.0)

    one = (np.float32([[0.0, 0.0, 0.0]]), np.float32([[0.1, 0.1, 0.1]]), np.uint16([50000]))
    got = sorter.sort(*_buffers(ctx, *one), 1, W2C, NEAR, CULL, 1 / 255)
    assert got.drawn() == 1 and got.indices().tolist() == [0] and _command(got) == (1, 1, 0, 0, 0)
    zmin, zmax = got.depth_range()
    assert zmin == zmax == pytest.approx(float(W2C[2, 3]), rel=1e-6)
    behind = (one[0] + np.float32([0.0, -20.0, 0.0]), one[1], one[2])
    assert sorter.sort(*_buffers(ctx, *behind), 1, W2C, NEAR, CULL, 1 / 255).drawn() == 0

    means, scales, opacity16 = _scene(5000, seed=4)
    means[:, 1] = -20.0 - np.abs(means[:, 1])  # all behind the camera (it looks along +y from y = -7)
    got, order, _ = _check_equal_to_torch(sorter, ctx, means, scales, opacity16)
    assert len(order) == 0 and _command(got) == (0, 1, 0, 0, 0)
    assert np.all(got.keys() == 65535)


def test_a_later_sort_invalidates_the_earlier_order(sorter, ctx) -> None:
    bufs = _buffers(ctx, *_scene(100, 1))
    first = sorter.sort(*bufs, 100, W2C, NEAR, None, 0.0)
    sorter.sort(*bufs, 100, W2C, NEAR, None, 0.0)
    with pytest.raises(RuntimeError, match="later"):
        first.drawn()


def test_large_dispatches_split_over_y(sorter, ctx, monkeypatch) -> None:
    """Counts beyond 65535 work groups per dimension: the same order with the limit made tiny."""
    means, scales, opacity16 = _scene(30_000, seed=5)
    expect = _check_equal_to_torch(sorter, ctx, means, scales, opacity16)[0].indices().copy()
    monkeypatch.setattr(gl_sort, "_MAX_GROUPS", 3)
    got = _check_equal_to_torch(sorter, ctx, means, scales, opacity16)[0].indices()
    assert np.array_equal(got, expect)


def test_the_indirect_command_draws_the_visible_gaussians(sorter, ctx) -> None:
    """render_indirect with the sort's element buffer and command lights exactly the pixels of
    the visible Gaussians (point i at pixel i of a 64 x 64 target), without the host's count."""
    n = 4096
    means, scales, opacity16 = _scene(n, seed=6)
    bufs = _buffers(ctx, means, scales, opacity16)
    got = sorter.sort(*bufs, n, W2C, NEAR, CULL, 1 / 255)
    prog = ctx.program(
        vertex_shader="""#version 430
        void main() {
            vec2 pixel = vec2(gl_VertexID % 64, gl_VertexID / 64) + 0.5;
            gl_Position = vec4(pixel / 32.0 - 1.0, 0.0, 1.0);
        }""",
        fragment_shader="""#version 430
        out vec4 color;
        void main() { color = vec4(1.0); }""",
    )
    vao = ctx.vertex_array(prog, [], index_buffer=got.index_buffer, index_element_size=4)
    fbo = ctx.framebuffer([ctx.renderbuffer((64, 64), 4)])
    fbo.use()
    fbo.clear()
    vao.render_indirect(got.indirect_buffer, moderngl.POINTS, count=1)
    lit = np.frombuffer(fbo.read(components=4), dtype=np.uint8).reshape(64 * 64, 4)[:, 0] > 0
    visible = _torch(means, scales, opacity16, W2C, CULL, 1 / 255)[0]
    assert 100 < len(visible) < n // 2
    assert np.array_equal(np.flatnonzero(lit), np.sort(visible))
    for obj in (vao, prog, fbo, *bufs):
        obj.release()


def test_alpha_threshold_is_the_float32_test_on_stored_opacities() -> None:
    levels = np.arange(65536, dtype=np.float32) / np.float32(65535)
    for min_alpha in (1 / 255, 0.3, 0.5, 2 / 3, 1.0, 1e-9):
        u = min_stored_opacity(min_alpha)
        assert levels[u] >= np.float32(min_alpha) > levels[u - 1]
    assert min_stored_opacity(0.0) == 0 and min_stored_opacity(1.5) == 65536


def test_needs_opengl_4_3() -> None:
    with pytest.raises(GLSortUnavailable, match="OpenGL 4.3"):
        GLDepthSort(types.SimpleNamespace(version_code=330))
