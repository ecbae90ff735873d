"""Replayed kernel launches, for the kernels a step runs every time over the same arrays.

Taichi 1.7 sets every argument of every launch from Python (per ndarray: type checks, the
template key, one setter call), and looks the compiled kernel up again; a step's kernel over a
body's ~30 ndarrays would spend more time there than computing on a small mesh. `replayed(kernel)`
records the launch context of a kernel's first launch with a given set of arguments (the same
argpack objects, the same template and scalar values) and replays it afterwards: the context
holds the arrays' addresses, not their contents, so a replay computes on the current data. After
the first launch each ndarray is set once more in the context by its host address (as Taichi does
for a numpy array), because the CPU launcher leaves the context holding allocation handles it has
already marked as addresses.
Arguments that are new objects (a re-allocated argpack after growth) record a new context; a
numpy argument is recorded by its address and shape, so a caller that reuses one buffer, filled
in place (or views of it of the same shape), replays too.

The context belongs to Taichi's internals (`taichi.lang.kernel_impl`, pinned to 1.7 by setup.cfg),
so replays are used on the CPU only, where the tests exercise them; other archs launch normally.

`host_view(ndarray)` is, on the CPU, a numpy array over an ndarray's own memory: reads without
Taichi's copy kernel (a parallel launch: milliseconds on busy cores), and BLAS on kernels' arrays.
`install()` (called by `tissue.backend.init`) makes every ndarray's `from_numpy` / `to_numpy` on
the CPU a numpy copy through that view: Taichi compiles a copy kernel per element type, shape and
dtype (about 11 of them on a scene's start, whose machine code every process makes again: see
bench.kernel_cost)
and launches one per call.
"""

from __future__ import annotations

import operator

import numpy as np
from taichi._lib import core as _ti_core
from taichi.lang import impl, runtime_ops
from taichi.lang._ndarray import Ndarray
from taichi.lang.argpack import ArgPack, ArgPackType
from taichi.lang.matrix import MatrixType
from taichi.lang.util import to_numpy_type
from taichi.types import primitive_types
from taichi.types import template

from . import backend


class _Recorder:
    """Stands in for Taichi's program during one launch, to keep what it launches."""

    def __init__(self, prog):
        self.prog, self.launched = prog, None

    def launch_kernel(self, compiled, context):
        self.launched = (compiled, context)
        self.prog.launch_kernel(compiled, context)

    def __getattr__(self, name):
        return getattr(self.prog, name)


class Replayed:
    def __init__(self, kernel):
        self.kernel = kernel
        self.primal = kernel._primal
        self.contexts: dict[tuple, tuple] = {}
        # The ids of arguments replayed before -> (those arguments, their context): a launch with
        # the very same objects skips making the key (reading a numpy array's address costs about
        # a microsecond). The entry keeps the objects alive, so an id found there is theirs.
        self._by_identity: dict[tuple, tuple] = {}

    def __call__(self, *args):
        if backend.current().arch != "cpu":
            return self.kernel(*args)
        ids = tuple(map(id, args))
        hit = self._by_identity.get(ids)
        if hit is None:
            key = tuple(_key(a) for a in args)
            if _UNREPLAYABLE in key:
                return self.kernel(*args)
            recorded = self.contexts.get(key)
            if recorded is None:
                return self._record(key, args)
            if len(self._by_identity) > 64:    # new argument objects every launch: keep the newest only
                self._by_identity.clear()
            hit = self._by_identity[ids] = (args, recorded)
        compiled, context, _ = hit[1]
        impl.get_runtime().prog.launch_kernel(compiled, context)
        return self._returns(context)

    def _record(self, key, args):
        runtime = impl.get_runtime()
        recorder = _Recorder(runtime.prog)
        runtime.prog = recorder
        try:
            result = self.kernel(*args)
        finally:
            runtime.prog = recorder.prog
        if recorder.launched is not None:
            if len(self.contexts) > 64:       # arguments that keep changing: keep the newest only
                self.contexts.clear()
                self._by_identity.clear()
            compiled, context = recorder.launched
            prog = recorder.prog
            for index, array in self._ndarray_slots(args):
                address = prog.get_ndarray_data_ptr_as_int(array.arr)
                context.set_arg_external_array_with_shape(index, address, array._get_nelement() * array._get_element_size(),
                                                          list(array.shape), 0)
            self.contexts[key] = (compiled, context, args)   # args: keeps the arrays alive
        return result

    def _ndarray_slots(self, args) -> list[tuple[tuple[int], Ndarray]]:
        """Each ndarray of the arguments with its slot in the launch context, in Taichi's order:
        top-level ndarrays at their argument's position (templates not counted), then those inside
        argpacks, depth first, after all arguments."""
        slots, packed, position = [], [], 0
        for arg, parameter in zip(args, self.primal.arguments):
            if isinstance(parameter.annotation, template):
                continue
            if isinstance(arg, Ndarray):
                slots.append(((position,), arg))
            elif isinstance(parameter.annotation, ArgPackType):
                packed.extend(_flatten(arg, parameter.annotation))
            position += 1
        return slots + [((position + j,), array) for j, array in enumerate(packed)]

    def _returns(self, context):
        # No sync before reading: replays run on the CPU only, where a launch returns when its
        # kernel has run (runtime_ops.sync would check Taichi's fields first, a few µs a launch).
        types = self.primal.return_type
        if types is None:
            return None
        values = [_read_return(self.primal, context, t, i) for i, t in enumerate(types)]
        return values[0] if len(values) == 1 else values


_UNREPLAYABLE = ("unreplayable",)


def _key(arg):
    """What identifies an argument's recorded launch: an argpack (or ndarray) by identity; a
    numpy array by where its memory is and its shape, which is all the launch keeps of it (so a
    new view of the same buffer, e.g. its first n² entries as n × n, replays too; one that is not
    C-contiguous is copied by Taichi at each launch, so it is never replayed); anything else by
    value."""
    if isinstance(arg, np.ndarray):
        if arg.flags.c_contiguous:
            return ("numpy", arg.__array_interface__["data"][0], arg.shape, arg.dtype.str)
        return _UNREPLAYABLE
    if isinstance(arg, (ArgPack, Ndarray)):
        return ("array", id(arg))
    return arg


def _flatten(pack: ArgPack, annotation: ArgPackType) -> list[Ndarray]:
    arrays = []
    for name, member in annotation.members.items():
        if isinstance(member, ArgPackType):
            arrays.extend(_flatten(pack[name], member))
        elif isinstance(pack[name], Ndarray):
            arrays.append(pack[name])
    return arrays


def _read_return(primal, context, kind, i):
    """A vector of floats as a tuple (Taichi builds a Matrix, which costs more than the step of a
    small mesh), anything else as Taichi reads it."""
    if isinstance(kind, MatrixType) and kind.ndim == 1 and kind.dtype in primitive_types.real_types:
        return tuple(context.get_struct_ret_float((i, j)) for j in range(kind.n))
    return primal.construct_kernel_ret(context, kind, (i,))


def kept_pack(kept, kind, arrays):
    """(argpack, its arrays): `kept` (such a pair, or None) when `arrays` holds the same objects,
    else `kind(**arrays)` anew. Building an argpack costs Taichi more than a replayed launch, and
    launches over a kept one replay. The arrays are compared by identity, one by one in C (ndarrays have no value
    equality): a tuple of their ids built in Python cost more, at every launch.
    `arrays`: {member: array}, or a tuple of the arrays in the order of `kind`'s members (cheaper
    to build, for a launch made every step)."""
    values = arrays if isinstance(arrays, tuple) else tuple(arrays.values())
    if kept is not None and len(values) == len(kept[1]) and all(map(operator.is_, values, kept[1])):
        return kept
    if isinstance(arrays, tuple):
        arrays = dict(zip(kind.members, arrays, strict=True))
    return kind(**arrays), values


def replayed(kernel) -> Replayed:
    """`kernel`, launched by replaying its recorded context when the arguments repeat."""
    return Replayed(kernel)


_original_copies = {name: getattr(Ndarray, name) for name in (
    "_ndarray_from_numpy", "_ndarray_to_numpy", "_ndarray_matrix_from_numpy", "_ndarray_matrix_to_numpy")}


def _on_cpu() -> bool:
    return impl.current_cfg().arch in (_ti_core.x64, _ti_core.arm64)


def _from_numpy(self, arr, as_vector=None):
    """Taichi's from_numpy (same checks, same casts: numpy's unsafe cast is C's, as the kernel's),
    as a numpy copy on the CPU."""
    if not (_on_cpu() and isinstance(arr, np.ndarray) and tuple(self.arr.total_shape()) == tuple(arr.shape)
            and arr.size):
        original = _original_copies["_ndarray_from_numpy" if as_vector is None else "_ndarray_matrix_from_numpy"]
        return original(self, arr) if as_vector is None else original(self, arr, as_vector)
    runtime_ops.sync()                    # kernels still writing it
    np.copyto(host_view(self), arr, casting="unsafe")


def _to_numpy(self, as_vector=None):
    if not (_on_cpu() and self._get_nelement()):
        original = _original_copies["_ndarray_to_numpy" if as_vector is None else "_ndarray_matrix_to_numpy"]
        return original(self) if as_vector is None else original(self, as_vector)
    runtime_ops.sync()
    return host_view(self).copy()


def install() -> None:
    """from_numpy / to_numpy of every ndarray as numpy copies on the CPU (idempotent; other archs,
    and empty arrays, keep Taichi's)."""
    Ndarray._ndarray_from_numpy = Ndarray._ndarray_matrix_from_numpy = _from_numpy
    Ndarray._ndarray_to_numpy = Ndarray._ndarray_matrix_to_numpy = _to_numpy


def host_view(array: Ndarray) -> np.ndarray:
    """A numpy array over a CPU ndarray's own memory (no copy): what numpy writes there, kernels
    read, and the other way round; a vector or matrix ndarray's element is its last axes. CPU
    only (elsewhere the memory is the device's). The view is valid while `array` lives: keep both."""
    if not _on_cpu():                     # Taichi's arch: where the memory really is
        raise RuntimeError("host_view: an ndarray's memory is the host's on the CPU backend only")
    import ctypes

    dtype = np.dtype(to_numpy_type(array.dtype))
    shape = tuple(array.arr.total_shape())
    address = impl.get_runtime().prog.get_ndarray_data_ptr_as_int(array.arr)
    buffer = (ctypes.c_char * (int(np.prod(shape)) * dtype.itemsize)).from_address(address)
    return np.frombuffer(buffer, dtype=dtype).reshape(shape)
