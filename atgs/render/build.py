"""Compile-at-first-use of the C++/OpenMP CPU kernels, cached by source hash.

Three extensions: the rasterizer (:data:`RASTER`, used by atgs.render.cpu), the feature-grid
encodings of the model (:data:`GRIDS`, used by atgs.model.grids) and the row-sparse Adam step
(:data:`SPARSE_ADAM`, used by atgs.train.optim). Each is built on its first use and imported
from the cache afterwards."""

from __future__ import annotations

from dataclasses import dataclass
import functools
import hashlib
import importlib.util
import platform
import sys
from pathlib import Path
from types import ModuleType

import torch

from atgs.io.cache import cache_dir

CSRC = Path(__file__).parent / "csrc"


@dataclass(frozen=True)
class Kernel:
    """One extension: its module-name prefix, sources and headers in csrc/, and what it is."""

    prefix: str
    sources: tuple[str, ...]
    headers: tuple[str, ...]
    what: str


RASTER = Kernel("atgs_raster", ("rasterize.cpp",), ("projection.h",), "the ATGS CPU rasterizer")
GRIDS = Kernel("atgs_grids", ("grids.cpp",), (), "the ATGS CPU grid encodings")
SPARSE_ADAM = Kernel("atgs_sparse_adam", ("sparse_adam.cpp",), (), "the ATGS CPU sparse Adam step")
BASE_CFLAGS = ("-O3", "-fopenmp", "-std=c++17")
LDFLAGS = ("-fopenmp",)


def cpu_flags() -> tuple[str, ...]:
    """AVX2/FMA when this CPU has them (the build is cached per machine, keyed by the flags)."""
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return ()
    try:
        words = set(Path("/proc/cpuinfo").read_text().split())
    except OSError:
        return ()
    return ("-mavx2", "-mfma") if {"avx2", "fma"} <= words else ()


def compile_flags() -> tuple[str, ...]:
    return BASE_CFLAGS + cpu_flags()


def cache_root() -> Path:
    """``torch_extensions`` in the ATGS cache (atgs.io.cache: $ATGS_CACHE_DIR, else ~/.cache/atgs)."""
    return cache_dir() / "torch_extensions"


def build_key(kernel: Kernel = RASTER) -> str:
    """Hash of the sources, flags, torch and Python versions: any change triggers a rebuild."""
    h = hashlib.sha256()
    for name in kernel.sources + kernel.headers:
        h.update((CSRC / name).read_bytes())
    h.update(repr((compile_flags(), LDFLAGS, torch.__version__, sys.version_info[:2])).encode())
    return h.hexdigest()[:16]


@functools.lru_cache(maxsize=None)
def load_extension(kernel: Kernel = RASTER) -> ModuleType:
    """Import the compiled extension, compiling it first if this source version is new."""
    name = f"{kernel.prefix}_{build_key(kernel)}"
    build_dir = cache_root() / name
    built = build_dir / f"{name}.so"
    if built.exists():  # the name is a hash of sources and flags: import without re-checking
        spec = importlib.util.spec_from_file_location(name, built)
        if spec is not None and spec.loader is not None:
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
            return module
    from torch.utils.cpp_extension import load

    build_dir.mkdir(parents=True, exist_ok=True)
    # stderr: stays visible when stdout is piped or captured
    print(f"compiling {kernel.what} (first use, up to a minute), cached in {build_dir}", file=sys.stderr, flush=True)
    return load(
        name=name,
        sources=[str(CSRC / s) for s in kernel.sources],
        extra_cflags=list(compile_flags()),
        extra_ldflags=list(LDFLAGS),
        build_directory=str(build_dir),
        verbose=False,
    )


@functools.lru_cache(maxsize=None)
def cpu_backend_error(kernel: Kernel = RASTER) -> str | None:
    """None if the extension loads, else a one-line reason (used by backend='auto', and by the
    grids to fall back to their torch version)."""
    try:
        load_extension(kernel)
    except Exception as exc:  # compiler missing, headers missing, ...
        return f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
    return None
