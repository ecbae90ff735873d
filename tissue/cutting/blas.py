"""C −= A Bᵀ in place on a block of a larger row-major matrix, through scipy's BLAS dgemm.

numpy's `C[i:j, k:l] -= A @ B.T` writes the product to a temporary first and then subtracts it
(the block's memory read twice and written twice, plus the temporary), and scipy.linalg.blas's
wrappers copy a block that is not contiguous. The BLAS itself takes a leading dimension, so this
calls it directly: scipy.linalg.cython_blas exports the function pointers (as PyCapsules) of the
BLAS scipy links, called here through ctypes. Its threads follow OPENBLAS_NUM_THREADS as numpy's.
"""

import ctypes

import numpy as np

_P = ctypes.c_void_p


def _blas_function(name: str, arguments: int):
    import scipy.linalg.cython_blas as cython_blas

    capsule = cython_blas.__pyx_capi__[name]
    get_name, get_pointer = ctypes.pythonapi.PyCapsule_GetName, ctypes.pythonapi.PyCapsule_GetPointer
    get_name.restype, get_name.argtypes = ctypes.c_char_p, [ctypes.py_object]
    get_pointer.restype, get_pointer.argtypes = ctypes.c_void_p, [ctypes.py_object, ctypes.c_char_p]
    return ctypes.CFUNCTYPE(None, *([_P] * arguments))(get_pointer(capsule, get_name(capsule)))


_dgemm = None


def _row_major(a: np.ndarray, name: str) -> int:
    """The leading dimension of a float64 array with unit column stride (BLAS reads it as its
    transpose, column-major)."""
    if a.dtype != np.float64 or a.ndim != 2 or (a.shape[1] > 1 and a.strides[1] != 8) or a.strides[0] % 8:
        raise ValueError(f"{name}: expected a float64 2-d array with contiguous rows, got {a.dtype} strides {a.strides}")
    return max(a.strides[0] // 8, 1)


def subtract_product(C: np.ndarray, A: np.ndarray, B: np.ndarray) -> None:
    """C −= A Bᵀ in place: C (m, n), A (m, k), B (n, k), views with contiguous rows of larger
    arrays (their row strides are passed as the leading dimensions, nothing is copied)."""
    global _dgemm
    m, n = C.shape
    k = A.shape[1]
    if A.shape != (m, k) or B.shape != (n, k):
        raise ValueError(f"subtract_product: shapes C {C.shape}, A {A.shape}, B {B.shape} do not match")
    if m == 0 or n == 0 or k == 0:
        return
    if _dgemm is None:
        _dgemm = _blas_function("dgemm", 13)
    ldc, lda, ldb = _row_major(C, "C"), _row_major(A, "A"), _row_major(B, "B")
    # Row-major C is column-major Cᵀ (n × m): Cᵀ −= B Aᵀ, i.e. dgemm("T", "N") on Bᵀ (k × n) and Aᵀ (k × m).
    integer, real = ctypes.c_int, ctypes.c_double
    _dgemm(ctypes.c_char_p(b"T"), ctypes.c_char_p(b"N"), ctypes.byref(integer(n)), ctypes.byref(integer(m)),
           ctypes.byref(integer(k)), ctypes.byref(real(-1.0)), _P(B.ctypes.data), ctypes.byref(integer(ldb)),
           _P(A.ctypes.data), ctypes.byref(integer(lda)), ctypes.byref(real(1.0)), _P(C.ctypes.data),
           ctypes.byref(integer(ldc)))
