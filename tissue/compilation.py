"""How long this process has spent compiling Taichi kernels, and how many kernel instances it compiled.

A Taichi kernel is compiled once per instance (template arguments, argument types) on its first
launch: `Kernel.materialize` turns the Python source into Taichi IR, then `Program.compile_kernel`
compiles that IR (or loads it from the offline cache on disk). `install()` (called by
`tissue.backend.init`) wraps `Kernel.materialize` so that it also does the second part at once and
adds the wall time of both to a process-wide total; the launch that follows finds the compiled
kernel in Taichi's in-memory cache. The time of the launches themselves is not counted.

    compilation.seconds(), compilation.count()   totals so far in this process
    start = compilation.snapshot(); ...; compilation.snapshot() - start   the share of a region

Not counted: the SNode trees' own compilation (fields), and, on CUDA, the
driver's loading of the compiled module, which happens on the first launch.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from taichi.lang import impl
from taichi.lang.kernel_impl import Kernel

_seconds = 0.0
_count = 0
_original_materialize = Kernel.materialize


@dataclass(frozen=True)
class Compiled:
    """Seconds spent compiling and kernel instances compiled (totals, or a difference of two)."""

    seconds: float
    count: int

    def __sub__(self, other: "Compiled") -> "Compiled":
        return Compiled(self.seconds - other.seconds, self.count - other.count)


def _materialize(self, key=None, args=None, arg_features=None):
    global _seconds, _count
    if key in self.compiled_kernels:            # every launch comes through here: stay cheap
        return _original_materialize(self, key, args, arg_features)
    self.runtime.materialize()                  # pending fields first: not kernel compilation
    before = len(self.compiled_kernels)
    start = time.perf_counter()
    _original_materialize(self, key, args, arg_features)
    if len(self.compiled_kernels) == before:    # key=None named an instance compiled already
        return
    kernel = next(reversed(self.compiled_kernels.values()))   # the one just added
    prog = impl.get_runtime().prog
    prog.compile_kernel(prog.config(), prog.get_device_caps(), kernel)
    _seconds += time.perf_counter() - start
    _count += 1


def install() -> None:
    """Start counting (idempotent)."""
    Kernel.materialize = _materialize


def seconds() -> float:
    """Wall time this process has spent compiling kernels (or loading them from the offline cache)."""
    return _seconds


def count() -> int:
    """Kernel instances this process has compiled (a kernel compiled again after `ti.reset` counts again)."""
    return _count


def snapshot() -> Compiled:
    return Compiled(_seconds, _count)
