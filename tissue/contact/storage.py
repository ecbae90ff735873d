"""Contact scratch storage by capacity: Taichi ndarrays that grow by doubling.

The number of contacts, rows and touched nodes changes from step to step, so the scratch the
contact kernels write grows now and then. Kernels take it as `ti.types.ndarray()`: compiled once per
element type and dimension, they serve arrays of any size, so growing never compiles (a new
`ti.field` is a new template argument: every kernel taking it would compile again).
"""

import taichi as ti


class Storage:
    """Named device arrays of at least a requested length; `growths` counts the reallocations."""

    def __init__(self):
        self.growths = 0
        self._arrays = {}

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
