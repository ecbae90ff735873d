"""How long this process has spent compiling Taichi kernels, and how many kernel instances it compiled.

A Taichi kernel is compiled once per instance (template arguments, argument types) on its first
launch, in three parts: `Kernel.materialize` turns the Python source into Taichi IR;
`Program.compile_kernel` compiles that IR to an LLVM module (or loads the module from the offline
cache on disk); and the first launch turns the module into machine code (LLVM's JIT on the CPU,
the driver's module load on CUDA), which the offline cache does not keep, so a warm start pays it
too. `install()` (called by `tissue.backend.init`) wraps `Kernel.materialize` so that it does the
first two parts at once, and `Kernel.launch_kernel` so that it times an instance's first launch
(to the end of the kernel: one run of it is included, milliseconds beside the seconds of code
generation). Process-wide totals:

    compilation.seconds(), compilation.count()   all three parts; kernel instances compiled
    compilation.snapshot()                       the same with the split (`.ir_seconds`: source to
                                                 IR to module; `.machine_code_seconds`: first launches)
    start = compilation.snapshot(); ...; compilation.snapshot() - start   the share of a region

Not counted: the SNode trees' own compilation (fields).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from taichi.lang import impl
from taichi.lang.kernel_impl import Kernel

_ir_seconds = 0.0
_machine_code_seconds = 0.0
_count = 0
_not_yet_launched: set[int] = set()       # ids of kernel instances compiled and not launched yet
_original_materialize = Kernel.materialize
_original_launch = Kernel.launch_kernel


@dataclass(frozen=True)
class Compiled:
    """Seconds spent compiling and kernel instances compiled (totals, or a difference of two)."""

    ir_seconds: float
    machine_code_seconds: float
    count: int

    @property
    def seconds(self) -> float:
        return self.ir_seconds + self.machine_code_seconds

    def __sub__(self, other: "Compiled") -> "Compiled":
        return Compiled(self.ir_seconds - other.ir_seconds, self.machine_code_seconds - other.machine_code_seconds,
                        self.count - other.count)


def _materialize(self, key=None, args=None, arg_features=None):
    global _ir_seconds, _count
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
    _ir_seconds += time.perf_counter() - start
    _count += 1
    _not_yet_launched.add(id(kernel))


def _launch_kernel(self, t_kernel, *args):
    global _machine_code_seconds
    if id(t_kernel) not in _not_yet_launched:
        return _original_launch(self, t_kernel, *args)
    _not_yet_launched.discard(id(t_kernel))
    start = time.perf_counter()
    result = _original_launch(self, t_kernel, *args)
    impl.get_runtime().prog.synchronize()
    _machine_code_seconds += time.perf_counter() - start
    return result


def install() -> None:
    """Start counting (idempotent)."""
    Kernel.materialize = _materialize
    Kernel.launch_kernel = _launch_kernel


def seconds() -> float:
    """Wall time this process has spent compiling kernels, all three parts."""
    return _ir_seconds + _machine_code_seconds


def count() -> int:
    """Kernel instances this process has compiled (a kernel compiled again after `ti.reset` counts again)."""
    return _count


def snapshot() -> Compiled:
    return Compiled(_ir_seconds, _machine_code_seconds, _count)
