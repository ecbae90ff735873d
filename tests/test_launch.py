"""tissue.launch's numpy copies for from_numpy / to_numpy on the CPU give what Taichi's copy kernels give."""

import numpy as np
import pytest
import taichi as ti

from tissue import compilation, launch


CASES = [   # (Taichi type, shape, numpy values' dtype): scalar, vector and matrix elements; casts
    (ti.f64, (5,), np.float64),
    (ti.i32, (2, 3), np.int64),
    (ti.f32, (4,), np.float64),
    (ti.types.vector(3, ti.f64), (6,), np.float64),
    (ti.types.vector(4, ti.i32), (3,), np.int32),
    (ti.types.matrix(3, 3, ti.f64), (2, 2), np.float64),
    (ti.types.matrix(3, 4, ti.f32), (3,), np.float64),
]


def _make(dtype, shape):
    return ti.ndarray(dtype, shape)


@pytest.mark.parametrize("dtype, shape, values_dtype", CASES)
def test_copies_equal_taichi_kernels(backend, dtype, shape, values_dtype):
    """Reference: Taichi's own copy kernels (the original methods), on the same values: random
    reals (rounded to f32 where the array is), and for integer arrays reals truncated as C casts."""
    ours, theirs = _make(dtype, shape), _make(dtype, shape)
    full_shape = tuple(ours.arr.total_shape())
    rng = np.random.default_rng(len(full_shape))
    values = (rng.standard_normal(full_shape) * 100).astype(values_dtype)
    ours.from_numpy(values)
    original_from = launch._original_copies["_ndarray_from_numpy" if len(full_shape) == len(shape)
                                            else "_ndarray_matrix_from_numpy"]
    original_to = launch._original_copies["_ndarray_to_numpy" if len(full_shape) == len(shape)
                                          else "_ndarray_matrix_to_numpy"]
    if len(full_shape) == len(shape):
        original_from(theirs, values)
        expected = original_to(theirs)
    else:
        as_vector = int(len(full_shape) == len(shape) + 1)
        original_from(theirs, values, as_vector)
        expected = original_to(theirs, as_vector)
    got = ours.to_numpy()
    assert got.dtype == expected.dtype and got.shape == expected.shape
    assert np.array_equal(got, expected)
    assert np.array_equal(theirs.to_numpy(), expected)   # the other way round too


def test_copies_compile_nothing_and_keep_taichi_checks(backend):
    a = ti.ndarray(ti.types.vector(2, ti.f64), 7)   # an element type no other test copies: Taichi's
    start = compilation.count()                      # kernels would compile an instance for it
    a.from_numpy(np.ones((7, 2)))
    assert a.to_numpy().sum() == 14.0
    assert compilation.count() == start
    with pytest.raises(ValueError, match="Mismatch shape"):   # Taichi's own message, from its method
        a.from_numpy(np.ones((6, 2)))
    with pytest.raises(TypeError):
        a.from_numpy([[1.0, 2.0]] * 7)
