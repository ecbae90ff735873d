"""The single place Taichi is initialised: arch and precision, chosen once per process.

Nothing initialises Taichi at import time. `init()` reads its arguments, else the environment
(`TISSUE_ARCH` = auto|cpu|cuda|vulkan, `TISSUE_PRECISION` = f64|f32), else the defaults
(auto arch = CUDA when present, else CPU; float64).

Taichi's own IR optimisation passes (`advanced_optimization`) are off unless
`TISSUE_ADVANCED_OPTIMIZATION` says otherwise: `1` runs them on every kernel, `auto` per kernel
(on, except for the kernel instances marked `compilation.without_ir_passes`: the step kernels of
multigrid schemes, where they cost minutes). LLVM optimises every kernel either way. Off is the
default because, measured, no kernel of the scenes steps enough faster with them to pay their
compile time (`python -m bench.compile_options`, bench/results/compile_options*.json).

Taichi's offline cache keeps at most 1 GiB (`OFFLINE_CACHE_BYTES`; Taichi's default is 100 MB and
evicts the least recently used quarter when full): one scene's serial step kernel alone is 7-10 MB,
so a handful of scenes and settings filled the default and sent the next run back to compiling.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import taichi as ti

from . import compilation, frontend
from .errors import TissueError

ARCHS = ("auto", "cpu", "cuda", "vulkan")
PRECISIONS = ("f64", "f32")
OFFLINE_CACHE_BYTES = 1 << 30
# Before any module of tissue defines its kernels: the decorators' class check is among what it makes cheap.
frontend.install()


@dataclass(frozen=True)
class Backend:
    arch: str        # the arch Taichi actually runs on: cpu, cuda or vulkan
    precision: str   # f64 or f32

    @property
    def real(self):
        """The Taichi float type of every simulation field."""
        return ti.f64 if self.precision == "f64" else ti.f32


_current: Backend | None = None


def _cuda_driver_loads() -> bool:
    """Whether the CUDA driver library loads, which Taichi opens by this name (its CUDADriver):
    where it does not, "auto" is the CPU without a trial start of Taichi on CUDA."""
    import ctypes

    try:
        ctypes.CDLL("nvcuda.dll" if os.name == "nt" else "libcuda.so")
    except OSError:
        return False
    return True


def _resolve_arch(name: str):
    if name == "auto":
        if not _cuda_driver_loads():
            return ti.cpu
        try:
            ti.init(arch=ti.cuda, offline_cache=True, log_level=ti.ERROR)
            ok = ti.lang.impl.current_cfg().arch == ti.cuda
        finally:
            ti.reset()
        return ti.cuda if ok else ti.cpu
    return {"cpu": ti.cpu, "cuda": ti.cuda, "vulkan": ti.vulkan}[name]


PASSES = ("auto", "0", "1")


def ir_passes() -> str:
    """TISSUE_ADVANCED_OPTIMIZATION: 0 (no kernel, the default), auto (per kernel) or 1 (every kernel)."""
    value = os.environ.get("TISSUE_ADVANCED_OPTIMIZATION", "0").lower()
    if value not in PASSES:
        raise TissueError(f"TISSUE_ADVANCED_OPTIMIZATION: expected auto, 0 or 1, got {value!r}")
    return value


def init(arch: str | None = None, precision: str | None = None, **kwargs) -> Backend:
    """Initialise Taichi (or keep the current initialisation if it already matches).

    Asking for a different arch or precision resets Taichi: every field made before is gone.
    """
    global _current
    arch = (arch or os.environ.get("TISSUE_ARCH") or "auto").lower()
    precision = (precision or os.environ.get("TISSUE_PRECISION") or "f64").lower()
    if arch not in ARCHS:
        raise TissueError(f"arch: unknown value {arch!r}; expected one of {', '.join(ARCHS)}")
    if precision not in PRECISIONS:
        raise TissueError(f"precision: unknown value {precision!r}; expected f64 or f32")
    if _current is not None and precision == _current.precision and arch in ("auto", _current.arch):
        return _current
    if _current is not None:
        ti.reset()
    passes = ir_passes()
    wanted = _resolve_arch(arch)
    fp = ti.f64 if precision == "f64" else ti.f32
    ti.init(arch=wanted, default_fp=fp, default_ip=ti.i32, offline_cache=True,
            offline_cache_max_size_of_files=OFFLINE_CACHE_BYTES, advanced_optimization=passes != "0",
            log_level=kwargs.pop("log_level", ti.WARN), **kwargs)
    compilation.install(per_kernel=passes == "auto")
    from . import launch    # (it imports this module)

    launch.install()
    got = ti.lang.impl.current_cfg().arch
    if got != wanted:
        ti.reset()
        _current = None
        raise TissueError(f"arch: {arch!r} is not available on this machine (Taichi fell back to {got.name})")
    _current = Backend(arch=got.name if got.name != "x64" else "cpu", precision=precision)
    if _current.arch == "arm64":
        _current = Backend(arch="cpu", precision=precision)
    return _current


def current() -> Backend:
    """The active backend, initialising with the defaults if nothing has yet."""
    return _current if _current is not None else init()


def sync() -> None:
    """Wait for the device: call before reading a clock. On the CPU a launch returns when its
    kernel has run, so there is nothing to wait for (ti.sync would still check Taichi's fields,
    and a contact step syncs six times)."""
    if current().arch != "cpu":
        ti.sync()

