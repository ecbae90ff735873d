"""Contact scratch storage by capacity: Taichi ndarrays that grow by doubling.

The number of contacts, rows and touched nodes changes from step to step, so the scratch the
contact kernels write grows now and then. Kernels take it as `ti.types.ndarray()`: compiled once per
element type and dimension, they serve arrays of any size, so growing never compiles (a new
`ti.field` is a new template argument: every kernel taking it would compile again). The same
arrays step after step also let a launch be replayed (tissue.launch).
"""

import numpy as np
import taichi as ti

from .. import backend
from ..launch import host_view


class Storage:
    """Named device arrays of at least a requested length; `growths` counts the reallocations."""

    def __init__(self):
        self.growths = 0
        self._arrays = {}
        self._views = {}

    def get(self, name, n: int, dtype) -> ti.Ndarray:
        """The array `name` with room for `n` elements along its first axis (contents not kept
        across a growth). First allocated at n; when short, at max(n, twice its capacity), so the
        reallocations of a growing demand stay few (amortised doubling)."""
        array = self._arrays.get(name)
        if array is not None and array.shape[0] >= n:
            return array
        if array is not None:
            self.growths += 1
            n = max(n, 2 * array.shape[0])
        array = self._arrays[name] = ti.ndarray(dtype, max(n, 1))
        return array

    def put(self, name, values: np.ndarray, dtype) -> ti.Ndarray:
        """The array `name` (as `get`) holding `values` in its first len(values) elements: on the
        CPU written through a numpy view of its memory kept with it (no copy kernel, no view made
        per call), elsewhere uploaded padded to its length."""
        array = self.get(name, len(values), dtype)
        if backend.current().arch == "cpu":
            kept = self._views.get(name)
            if kept is None or kept[0] is not array:
                kept = self._views[name] = (array, host_view(array))
            kept[1][:len(values)] = values
        else:
            padded = np.zeros((array.shape[0],) + np.shape(values)[1:], np.asarray(values).dtype)
            padded[:len(values)] = values
            array.from_numpy(padded)
        return array
