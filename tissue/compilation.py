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
    compilation.seconds_by_kernel(cpu=False)     the first two parts per kernel function, wall or
                                                 the process's CPU seconds (what load does not inflate)
    compilation.instances()                      per kernel instance, CPU seconds of each part:
                                                 front end (source to IR), module, machine code

Not counted: the SNode trees' own compilation (fields).

Taichi's IR passes (`advanced_optimization`) per kernel: Taichi reads the compile config when it
compiles a kernel, and hashes it into the kernel's cache key, which it keeps on the kernel object
and reuses at every later launch. So `install(per_kernel=True)` compiles the kernel instances
marked by `without_ir_passes` with the passes off, the others with the process's setting, and each
keeps what it was compiled with, in memory and in the offline cache (keys differ by the setting).
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass

from taichi.lang import impl
from taichi.lang.kernel_impl import Kernel

_ir_seconds = 0.0
_machine_code_seconds = 0.0
_count = 0
_not_yet_launched: set[int] = set()       # ids of kernel instances compiled and not launched yet
_original_materialize = Kernel.materialize
_original_launch = Kernel.launch_kernel
_by_kernel: dict[str, list[float]] = {}   # [wall, CPU] seconds per kernel function, over its instances
_per_kernel = False
_without_passes: dict = {}                # Taichi Kernel -> which instances (by their arguments) compile without
_instances: dict[int, "Instance"] = {}    # id of the compiled kernel -> its record, in compilation order


@dataclass
class Instance:
    """One compiled kernel instance: CPU seconds of the process in each part of its compilation."""

    kernel: str
    frontend_s: float = 0.0        # Python source to Taichi IR (every process)
    module_s: float = 0.0          # IR to LLVM module, or the offline cache's copy
    machine_code_s: float = 0.0    # the first launch: machine code (not cached), and one run


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
    start, cpu = time.perf_counter(), time.process_time()
    _original_materialize(self, key, args, arg_features)
    if len(self.compiled_kernels) == before:    # key=None named an instance compiled already
        return
    frontend_cpu = time.process_time()
    kernel = next(reversed(self.compiled_kernels.values()))   # the one just added
    prog = impl.get_runtime().prog
    with _passes_for(self, args):
        prog.compile_kernel(prog.config(), prog.get_device_caps(), kernel)
    elapsed = time.perf_counter() - start
    _ir_seconds += elapsed
    _count += 1
    _not_yet_launched.add(id(kernel))
    _instances[id(kernel)] = Instance(self.func.__name__, frontend_cpu - cpu, time.process_time() - frontend_cpu)
    totals = _by_kernel.setdefault(self.func.__name__, [0.0, 0.0])
    totals[0] += elapsed
    totals[1] += time.process_time() - cpu


@contextmanager
def _passes_for(kernel: Kernel, args):
    """The process's compile config, with the IR passes off while a marked kernel instance compiles."""
    config = impl.current_cfg()
    when = _without_passes.get(kernel)
    if not (_per_kernel and config.advanced_optimization and when is not None and when(*args)):
        yield
        return
    config.advanced_optimization = False
    try:
        yield
    finally:
        config.advanced_optimization = True


def without_ir_passes(when=lambda *args: True):
    """A decorator (above `@ti.kernel`): compile the kernel's instances for which `when(*arguments of
    the launch)` holds without Taichi's IR passes, when the passes are chosen per kernel. For kernels
    so large that the passes cost minutes."""
    def mark(kernel):
        _without_passes[kernel._primal] = when
        return kernel
    return mark


def _launch_kernel(self, t_kernel, *args):
    global _machine_code_seconds
    if id(t_kernel) not in _not_yet_launched:
        return _original_launch(self, t_kernel, *args)
    _not_yet_launched.discard(id(t_kernel))
    start, cpu = time.perf_counter(), time.process_time()
    result = _original_launch(self, t_kernel, *args)
    impl.get_runtime().prog.synchronize()
    _machine_code_seconds += time.perf_counter() - start
    _instances[id(t_kernel)].machine_code_s = time.process_time() - cpu
    return result


def install(per_kernel: bool | None = None) -> None:
    """Start counting (idempotent); `per_kernel`: honour `without_ir_passes` (None: as before)."""
    global _per_kernel
    if per_kernel is not None:
        _per_kernel = per_kernel
    Kernel.materialize = _materialize
    Kernel.launch_kernel = _launch_kernel


def seconds() -> float:
    """Wall time this process has spent compiling kernels, all three parts."""
    return _ir_seconds + _machine_code_seconds


def count() -> int:
    """Kernel instances this process has compiled (a kernel compiled again after `ti.reset` counts again)."""
    return _count


def seconds_by_kernel(cpu: bool = False) -> dict[str, float]:
    """Seconds of source to module per kernel function name (all its instances) in this process:
    wall, or CPU of the process (what a loaded machine does not inflate)."""
    return {name: totals[1 if cpu else 0] for name, totals in _by_kernel.items()}


def instances() -> list[Instance]:
    """Every kernel instance this process compiled, in order, with the CPU seconds of each part."""
    return list(_instances.values())


def snapshot() -> Compiled:
    return Compiled(_ir_seconds, _machine_code_seconds, _count)
