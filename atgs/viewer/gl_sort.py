"""The depth sort and cull of :mod:`viewer.sorting` in OpenGL 4.3 compute shaders, for Gaussians
that live only in GL buffers (decoded there): it writes the element buffer and an indexed
indirect draw command on the GPU, so a frame needs no readback to the host.

Semantics are those of ``sorting._back_to_front(..., exact=False)``: the same near, alpha and
frustum tests (the planes from ``sorting._cull_planes``, passed as float32 uniforms), 16-bit
keys ``floor(clamp((zmax - z) 65534 / (zmax - zmin), 0, 65534))`` (culled 65535), a stable
ascending sort of the keys, and the visible Gaussians first. The alpha test compares the
stored 16-bit opacity with the smallest 16-bit value whose float32 ``o / 65535`` reaches
``float32(min_alpha)`` (computed on the host): exactly torch's test on the stored opacity.
Two differences, both rounding: the key scale is divided in float32 on the GPU (torch divides
in float64 and rounds to float32), so a key at a floor boundary can be one level away from
torch's; and z and the plane values are ``w + fma(c, z, fma(b, y, a x))``, the order torch's
addmm (MKL) rounds the cull rows in, if the driver fuses ``fma`` (llvmpipe does not, which is
how MKL rounds the depth row alone). Measured on llvmpipe: 0-0.5% of the keys one level off,
the visible sets equal (tests/test_viewer_gl_sort.py).

Passes (``atgs/shaders/sort_*.comp``; a storage barrier between dispatches, no readback):

1. ``sort_stats`` (RESET): zero the count, depth range and scale.
2. ``sort_depth``: per Gaussian the cull and z, as an order-preserving uint (so atomicMin/Max
   give the range; one global atomic per work group); culled ones get 0xFFFFFFFF.
3. ``sort_stats``: the key scale from the range, in float32, and the indirect draw command.
4. ``sort_keys``: the 16-bit keys, in place of the depths.
5. Two LSD radix passes of 8 bits, each ``sort_histogram`` (per block of ``block_size`` items,
   digit counts, digit-major), ``sort_scan`` (exclusive prefix sum of those counts, three
   dispatches) and ``sort_scatter``. One invocation walks one block in order, for the counts
   and for the scatter, so the scatter is stable by construction and the whole sort is
   deterministic (the only atomics are the count, min and max of step 2, which commute).
   The first pass reads the keys and writes (key, index) pairs; the second writes only the
   indices, into the element buffer.

All Gaussians are sorted (culled ones carry key 65535 to the end), so every dispatch size
depends only on ``count``: the host never needs the visible count.

Block size B. There are N / B sequential walkers, each B steps long, and 256 N / B counts to
scan. Measured on llvmpipe (2 cores, bench/gl_sort.py: 1920x1080, median ms of the whole sort
at B = 128, 256, 512, 1024, 2048, four runs): 100k Gaussians 7.6-13, 7.5-10, 5.4-8.4, 6.4-8.0,
6.4-7.4; 1M 54-80, 41-54, 37-39, 35-36, 34-36. A CPU wants few, long walkers (2 cores x 8
SIMD lanes) and a small scan, so it gains up to 1024. A GPU wants thousands of walkers in
flight, since each walker's B steps are latency bound (a local-memory counter update each, a
cache miss every 32 keys: at an estimated 25-50 cycles a step, unmeasured here for want of a
GPU, B = 512 is 10-20 us a pass), while the
scan (bandwidth bound, 256 N / B entries) should stay below the key array's size. B = 512 is
the default: within ~10% of the best on llvmpipe, a scan of N / 2 entries, and 2k walkers at
1M Gaussians (20k at 10M) on a GPU. (A GPU-tuned sort would rank digits inside a work group
for coalesced loads; this is the simple, portable, stable design.) The scan works in
sequential chunks of 32 counts per invocation, with one work group scanning the chunk sums:
work-group barriers are what llvmpipe pays most for (a Hillis-Steele scan per 1024 counts
took 45 ms per 1M counts there; this takes ~3 ms).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import moderngl
import numpy as np

from atgs.viewer.sorting import FrustumCull, _cull_planes
from atgs.shaders import load_shader

BLOCK_SIZE = 512  # items per sequential walker in the radix passes (module docstring)
MIN_GL_VERSION = 430  # compute shaders and shader storage buffers
_GROUP = 256  # local size of the per-Gaussian passes (sort_depth, sort_keys, sort_scan)
_WALKER_GROUP = 64  # local size of sort_histogram and sort_scatter
_SCAN_CHUNK = 32  # counts per invocation in sort_scan
_MAX_GROUPS = 65535  # GL's guaranteed minimum of GL_MAX_COMPUTE_WORK_GROUP_COUNT per dimension
_STORAGE = moderngl.SHADER_STORAGE_BARRIER_BIT
_DONE = (moderngl.SHADER_STORAGE_BARRIER_BIT | moderngl.ELEMENT_ARRAY_BARRIER_BIT | moderngl.COMMAND_BARRIER_BIT
         | moderngl.BUFFER_UPDATE_BARRIER_BIT)  # what the draw and the readbacks of the results need


class GLSortUnavailable(RuntimeError):
    """The context cannot run the GL depth sort (it needs OpenGL 4.3 compute shaders)."""


def _from_ordered(bits: int) -> float:
    """Inverse of sort_depth.comp's order-preserving float -> uint map."""
    raw = bits & 0x7FFFFFFF if bits & 0x80000000 else ~bits & 0xFFFFFFFF
    return float(np.array([raw], dtype=np.uint32).view(np.float32)[0])


@functools.cache
def _opacity_levels() -> np.ndarray:
    """float32 o / 65535 of every stored opacity o, as the torch side computes them."""
    return np.arange(65536, dtype=np.float32) / np.float32(65535.0)


def min_stored_opacity(min_alpha: float) -> int:
    """Smallest stored opacity o (uint16) with float32(o) / 65535 >= float32(min_alpha), 65536
    if none; 0 when ``min_alpha <= 0`` (no alpha cull, as in sorting)."""
    if min_alpha <= 0.0:
        return 0
    return int(np.searchsorted(_opacity_levels(), np.float32(min_alpha), side="left"))


@dataclass
class GLOrder:
    """The result of :meth:`GLDepthSort.sort`, on the GPU. Valid until the sorter's next sort
    (its buffers are reused); the three readbacks are the only syncs with the GPU."""

    index_buffer: moderngl.Buffer
    """uint32, room for ``count``: the visible Gaussians' indices first, farthest first."""
    indirect_buffer: moderngl.Buffer
    """(drawn, 1, 0, 0, 0): ``vao.render_indirect(indirect_buffer, moderngl.POINTS, count=1)``."""
    count: int
    _sorter: GLDepthSort = field(repr=False)
    _generation: int = field(repr=False)

    def _check(self) -> None:
        if self._generation != self._sorter.generation:
            raise RuntimeError("this GLOrder was overwritten by a later GLDepthSort.sort")

    def drawn(self) -> int:
        """Number of visible Gaussians (reads the draw command back)."""
        self._check()
        return int(np.frombuffer(self.indirect_buffer.read(4), dtype=np.uint32)[0])

    def depth_range(self) -> tuple[float, float]:
        """(zmin, zmax) of the visible Gaussians' view depths; (0.0, 0.0) when none is visible."""
        self._check()
        count, zmin, zmax, _ = (int(v) for v in np.frombuffer(self._sorter.stats.read(16), dtype=np.uint32))
        return (_from_ordered(zmin), _from_ordered(zmax)) if count else (0.0, 0.0)

    def indices(self) -> np.ndarray:
        """int32 copy of the first ``drawn()`` entries of the element buffer."""
        n = self.drawn()
        if not n:
            return np.zeros(0, dtype=np.int32)
        return np.frombuffer(self.index_buffer.read(4 * n), dtype=np.uint32).astype(np.int32)

    def keys(self) -> np.ndarray:
        """The 16-bit key of each Gaussian, by index (65535: culled); for tests."""
        self._check()
        if not self.count:
            return np.zeros(0, dtype=np.uint32)
        return np.frombuffer(self._sorter.buffers["keys"].read(4 * self.count), dtype=np.uint32).copy()


class GLDepthSort:
    """Depth sort and cull on the GL (module docstring). Use from the thread that owns ``ctx``;
    reuses its buffers across calls, growing them in powers of two. ``allocations`` counts the
    buffers made: a VAO holding the element buffer must be rebuilt when it changes."""

    def __init__(self, ctx: moderngl.Context, block_size: int = BLOCK_SIZE) -> None:
        if ctx.version_code < MIN_GL_VERSION:
            raise GLSortUnavailable(
                f"the GL depth sort needs OpenGL 4.3 (compute shaders, storage buffers); this context is "
                f"{ctx.version_code // 100}.{ctx.version_code % 100 // 10}")
        if block_size < 1:
            raise ValueError(f"block_size {block_size}: must be positive")
        self.ctx = ctx
        self.block_size = block_size
        self.generation = 0
        self.allocations = 0
        walker = {"BLOCK_SIZE": f"{block_size}u"}
        cs = ctx.compute_shader
        self._reset = cs(load_shader("sort_stats.comp", {"RESET": 1}))
        self._finish = cs(load_shader("sort_stats.comp", {"RESET": 0}))
        self._depth = cs(load_shader("sort_depth.comp"))
        self._keys = cs(load_shader("sort_keys.comp"))
        self._histogram = [cs(load_shader("sort_histogram.comp", {**walker, "INPUT_PAIRS": p})) for p in (0, 1)]
        self._scatter = [cs(load_shader("sort_scatter.comp", {**walker, "INPUT_PAIRS": p, "OUTPUT_PAIRS": 1 - p}))
                         for p in (0, 1)]
        self._scan = [cs(load_shader("sort_scan.comp", {"STAGE": s, "CHUNK": f"{_SCAN_CHUNK}u"})) for s in (1, 2, 3)]
        self.stats = ctx.buffer(reserve=16)  # count, zmin, zmax (ordered uints), scale
        self.command = ctx.buffer(reserve=20)  # the indexed indirect draw command
        self.buffers: dict[str, moderngl.Buffer] = {}

    # --- buffers --------------------------------------------------------------------------
    def _fit(self, name: str, nbytes: int) -> moderngl.Buffer:
        """The named buffer with room for ``nbytes`` (a new one, a power of two, if it had not)."""
        buf = self.buffers.get(name)
        if buf is None or buf.size < nbytes:
            if buf is not None:
                buf.release()
            self.allocations += 1
            buf = self.buffers[name] = self.ctx.buffer(reserve=max(1 << max(0, (nbytes - 1).bit_length()), 4096))
        return buf

    # --- dispatch -------------------------------------------------------------------------
    def _run(self, program: moderngl.ComputeShader, buffers: list[moderngl.Buffer], items: int, local: int,
             **uniforms: object) -> None:
        """Bind ``buffers`` to storage bindings 0.. in order, set ``uniforms``, dispatch one
        invocation per item (groups beyond GL's guaranteed 65535 per dimension go to y; the
        shaders' ``item_index`` undoes it), then a storage barrier."""
        for binding, buf in enumerate(buffers):
            buf.bind_to_storage_buffer(binding)
        for name, value in uniforms.items():
            member = program.get(name, None)
            if member is not None:  # a uniform the compiler removed is not an error
                member.value = value
        groups = max(1, -(-items // local))
        rows = -(-groups // _MAX_GROUPS)
        program.run(-(-groups // rows), rows)
        self.ctx.memory_barrier(_STORAGE)

    def sort(self, means: moderngl.Buffer, scales: moderngl.Buffer, opacity_rgb: moderngl.Buffer, count: int,
             w2c: np.ndarray, near: float, cull: FrustumCull | None, min_alpha: float) -> GLOrder:
        """Cull and sort ``count`` Gaussians held in the packing layout (means and scales float32
        x3, opacity_rgb uint16 x4) for the camera ``w2c``; issues GPU work only (no readback)."""
        if count < 0:
            raise ValueError(f"count {count}: must be >= 0")
        for name, buf, stride in (("means", means, 12), ("scales", scales, 12), ("opacity_rgb", opacity_rgb, 8)):
            if count and buf.size < stride * count:
                raise ValueError(f"{name}: {buf.size} bytes hold fewer than {count} Gaussians of {stride} bytes")
        self.generation += 1
        n = int(count)
        index = self._fit("index", 4 * n)
        self.ctx.memory_barrier(_STORAGE)  # inputs written by other shaders (the decoder) are visible
        self._run(self._reset, [self.stats], 1, 1)
        if n:
            self._cull_and_depth(means, scales, opacity_rgb, n, w2c, near, cull, min_alpha)
        self._run(self._finish, [self.stats, self.command], 1, 1)
        if n:
            self._run(self._keys, [self.buffers["keys"], self.stats], n, _GROUP, u_count=n)
            self._radix(n, index)
        self.ctx.memory_barrier(_DONE)
        return GLOrder(index, self.command, n, self, self.generation)

    def _cull_and_depth(self, means: moderngl.Buffer, scales: moderngl.Buffer, opacity_rgb: moderngl.Buffer,
                        n: int, w2c: np.ndarray, near: float, cull: FrustumCull | None, min_alpha: float) -> None:
        w = np.asarray(w2c, dtype=np.float64)
        planes, factor = np.zeros((4, 4)), 0.0
        if cull is not None:
            normals, offsets, factor = _cull_planes(w, cull)
            planes = np.concatenate([normals, offsets[:, None]], axis=1)
        keys = self._fit("keys", 4 * n)
        # float32 as torch's _affine_rows converts them
        self._run(self._depth, [means, scales, opacity_rgb, keys, self.stats], n, _GROUP, u_count=n,
                  u_depth_row=tuple(float(v) for v in w[2].astype(np.float32)),
                  u_planes=[tuple(float(v) for v in row) for row in planes.astype(np.float32)],
                  u_extent_factor=float(np.float32(factor)), u_cull=cull is not None,
                  u_near=float(np.float32(near)), u_min_opacity=min_stored_opacity(min_alpha))

    def _radix(self, n: int, index: moderngl.Buffer) -> None:
        """Two stable 8-bit passes: keys -> (key, index) pairs by the low byte -> indices by the high."""
        blocks = -(-n // self.block_size)
        entries = 256 * blocks
        keys = self.buffers["keys"]
        pairs = self._fit("pairs", 8 * n)
        counts = self._fit("counts", 4 * entries)
        chunks = -(-entries // _SCAN_CHUNK)
        partials = self._fit("partials", 4 * chunks)
        for p, (source, target) in enumerate(((keys, pairs), (pairs, index))):
            walk = dict(u_count=n, u_blocks=blocks, u_shift=8 * p)
            self._run(self._histogram[p], [source, counts], blocks, _WALKER_GROUP, **walk)
            self._run(self._scan[0], [counts, partials], chunks, _GROUP, u_count=entries)
            self._run(self._scan[1], [counts, partials], 1, _GROUP, u_count=entries)
            self._run(self._scan[2], [counts, partials], chunks, _GROUP, u_count=entries)
            self._run(self._scatter[p], [source, counts, target], blocks, _WALKER_GROUP, **walk)

    def release(self) -> None:
        for obj in (self._reset, self._finish, self._depth, self._keys, *self._histogram, *self._scatter,
                    *self._scan, self.stats, self.command, *self.buffers.values()):
            obj.release()
        self.buffers.clear()
