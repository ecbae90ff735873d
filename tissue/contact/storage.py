"""Contact scratch storage by capacity: arrays that grow by doubling, and the argpacks over them.

The number of contacts, rows and touched nodes changes from step to step, so the scratch the
contact kernels write grows now and then. Kernels take it as `ti.types.ndarray()`: compiled once per
element type and dimension, they serve arrays of any size, so growing never compiles (a new
`ti.field` is a new template argument: every kernel taking it would compile again). The same
arrays step after step, bundled in argpacks kept with them (`pack`), also let a launch be replayed
(tissue.launch).

Arrays are Taichi ndarrays, or numpy arrays (`HostArray`): with `host` on the CPU, with `numpy` on
every arch. Kernels read and write those in place (on a GPU, Taichi copies them there and back at
each launch), and one costs a small fraction of a Taichi ndarray's allocation, which matters to
callers that make a storage per problem (the frictional contact solver's API).
"""

import numpy as np
import taichi as ti

from .. import backend
from ..launch import host_view, kept_pack


class HostArray(np.ndarray):
    """A numpy array with the Taichi ndarray methods used here (in place: no copies)."""

    def from_numpy(self, a):
        self[...] = a

    def to_numpy(self):
        return np.array(self)

    def copy_from(self, other):
        self[...] = other


# Elements a named array is first allocated with at least: a Taichi ndarray is slow to allocate,
# and each growth rebuilds the argpacks over it and records their launches again, in the step that
# grows (the pressed liver's per-row arrays grew 2-5 times each from its first
# contacts; from 256, its per-row and per-block arrays still grew once each, at 85 contacts).
FIRST_ROOM = 1024


def _numpy_type(dtype):
    return np.int32 if dtype == ti.i32 else (np.float64 if dtype == ti.f64 else np.float32)


class Storage:
    """Named device arrays of at least a requested length; `growths` counts the reallocations."""

    def __init__(self, host: bool = False, numpy: bool = False):
        """host: numpy arrays on the CPU (HostArray), Taichi ndarrays elsewhere; numpy: numpy
        arrays on every arch (for a launch that takes them as they are: on a GPU, Taichi copies
        them there and back at each launch)."""
        self._growths = 0
        self.host = numpy or (host and backend.current().arch == "cpu")
        self._arrays = {}
        self._views = {}
        self._packs = {}
        self._children = {}
        self._owner = None

    @property
    def growths(self) -> int:
        return self._growths + sum(child.growths for child in self._children.values())

    def claim(self, owner) -> bool:
        """`owner` (a solver) is to write these arrays: whether it was the last to claim them, so
        that what it wrote there before is still there."""
        was, self._owner = self._owner is owner, owner
        return was

    def child(self, name) -> "Storage":
        """A storage of the same kind kept in this one under `name` (a nested solver's arrays);
        its growths count as this one's."""
        kept = self._children.get(name)
        if kept is None:
            kept = self._children[name] = Storage(numpy=self.host)
        return kept

    def get(self, name, n: int, dtype, tail: tuple = ()):
        """The array `name` with room for `n` elements along its first axis, of shape (capacity,)
        + tail (contents not kept across a growth). First allocated at max(n, FIRST_ROOM); when
        short, at max(n, twice its capacity), so the reallocations of a growing demand stay few
        (amortised doubling; a contact stage's first contacts are a few, its pressed ones a few
        hundred); allocated anew at n when `tail` changes."""
        array = self._arrays.get(name)
        tail = tuple(tail)
        if array is not None and array.shape[1:] == tail and array.shape[0] >= n:
            return array
        if array is None:
            n = max(n, FIRST_ROOM)
        else:
            self._growths += 1
            if array.shape[1:] == tail:
                n = max(n, 2 * array.shape[0])
        shape = (max(n, 1),) + tail
        if self.host:
            array = np.zeros(shape, _numpy_type(dtype)).view(HostArray)
        else:
            array = ti.ndarray(dtype, shape)
        self._arrays[name] = array
        return array

    def put(self, name, values: np.ndarray, dtype, tail: tuple = ()):
        """The array `name` (as `get`) holding `values` in its first len(values) elements: on the
        CPU written through a numpy view of its memory kept with it (no copy kernel, no view made
        per call), elsewhere uploaded padded to its length."""
        array = self.get(name, len(values), dtype, tail)
        if self.host:
            array[:len(values)] = values
        elif backend.current().arch == "cpu":
            self.view(name)[:len(values)] = values
        else:
            padded = np.zeros((array.shape[0],) + np.shape(values)[1:], np.asarray(values).dtype)
            padded[:len(values)] = values
            array.from_numpy(padded)
        return array

    def view(self, name) -> np.ndarray:
        """The array `name` as numpy over its own memory (CPU only; kept, and remade after a
        growth): what is written there, kernels read."""
        array = self._arrays[name]
        if self.host:
            return array
        kept = self._views.get(name)
        if kept is None or kept[0] is not array:
            kept = self._views[name] = (array, host_view(array))
        return kept[1]

    def pack(self, name, kind, **arrays):
        """The argpack `kind` over `arrays`, kept under `name` and built again only when one of
        them is another object (after a growth): building one costs Taichi more than a replayed
        launch, and launches over a kept one replay (tissue.launch.kept_pack)."""
        kept = self._packs[name] = kept_pack(self._packs.get(name), kind, arrays)
        return kept[0]
