"""tissue.frontend's memoised source positions and source reads give Taichi exactly what it computed itself,
and its directly built matrix operations the bits Taichi's own compute."""

import functools
import textwrap
from pathlib import Path

import numpy as np
import taichi as ti
from taichi.lang.ast import ast_transformer_utils

from tissue import backend, frontend


@ti.func
def _spread(a: ti.template(), i):
    """Multi-line statements, a loop and a branch: the node kinds get_pos_info treats apart."""
    s = 0.0
    for j in range(3):
        if a[i] > j:
            s += (a[i]
                  * j)
    return s


def _kernel():
    # A fresh kernel object per call: Taichi transforms its source again (no in-memory hit).
    @ti.kernel
    def spread_twice(a: ti.types.ndarray()) -> ti.f64:
        total = 0.0
        for i in range(a.shape[0]):
            total += _spread(a, i) + _spread(a, i)   # inlined twice: the second reads the memo
        return total
    return spread_twice


def test_memoised_positions_equal_taichi_own(monkeypatch):
    backend.init("cpu")
    frontend.install()
    compared = []

    def checked(ctx, node):
        memo = frontend._get_pos_info(ctx, node)
        ast_transformer_utils.TextWrapper = textwrap.TextWrapper      # Taichi's own, wrapper included
        try:
            compared.append(memo == frontend._original_pos_info(ctx, node))
        finally:
            ast_transformer_utils.TextWrapper = frontend._wrapper
        return memo

    monkeypatch.setattr(ast_transformer_utils.ASTTransformerContext, "get_pos_info", checked)
    values = [0.0, 1.0, 2.0, 3.0]
    a = ti.ndarray(ti.f64, 4)
    a.from_numpy(np.array(values))
    expected = 2 * sum(v * j for v in values for j in range(3) if v > j)
    for _ in range(2):
        assert _kernel()(a) == expected
    assert len(compared) > 20 and all(compared)


def test_memoised_source_equals_inspect_and_is_a_fresh_list():
    lines, start = frontend._getsourcelines_list(_kernel)
    assert (lines, start) == frontend._original_sourcelines(_kernel) and lines[0].startswith("def _kernel")
    lines.clear()                                   # a caller's edit does not reach the memo
    assert frontend._getsourcelines_list(_kernel)[0] == frontend._original_sourcelines(_kernel)[0]


def _probe(seen):
    """Asks as Taichi's decorators do: is the line two frames up (where this is called) a class statement?"""
    seen.append((frontend._inside_class(2), frontend._original_inside_class(2)))


def test_class_check_equals_taichi_own():
    seen = []

    class Inside: _probe(seen)   # noqa: E701 (one line: the line asked about is a class statement)

    _probe(seen)
    assert seen == [(True, True), (False, False)]
    assert frontend._inside_class(10_000) is False     # no frame that far up, as Taichi answers


def test_fast_wrapper_equals_textwrap():
    """get_pos_info wraps each source line and its caret line at 80 columns: every line of tissue's
    own source, its caret-line shapes, and the cases the fast path leaves to TextWrapper (tabs,
    other whitespace, non-ASCII, longer than 80 columns), each twice: the second from its memo."""
    lines = [line for path in sorted(Path(frontend.__file__).parent.rglob("*.py"))
             for line in path.read_text().splitlines()]
    shapes = [" " * 4 + "^" * 10, " " * 8 + "^" * 3 + " " * 20, "^" * 80, " " * 80, ""]
    edges = ["x" * 80, "x" * 81, "x" * 79 + "  ", "    " + "y " * 40, "a\tb", "\tif a:", "a\x0cb", "a\x1fb", "é = 1",
             "a \u3000", "long-hyphenated-" * 6, "  x = 1   ", "   "]
    wrapper, fast = textwrap.TextWrapper(width=80), frontend._Wrapper(width=80)
    assert len(lines) > 1000
    for text in (lines + shapes + edges) * 2:
        assert fast.wrap(text) == wrapper.wrap(text), repr(text)
    fast.wrap("x" * 81).append("changed by its caller")
    assert fast.wrap("x" * 81) == wrapper.wrap("x" * 81)


def test_memoised_fill_equals_textwrap():
    import textwrap

    for line in ("\tif a:\t# tab", "    x = 1", ""):
        assert frontend._fill(line, tabsize=4, width=9999) == textwrap.fill(line, tabsize=4, width=9999)


def _matrix_kernel():
    """A fresh kernel object (compiled at its first call) using every directly built operation,
    on square and non-square shapes, floats and integers, and one Taichi keeps (vector @ matrix)."""
    @ti.kernel
    def matrix_ops_kernel(a: ti.types.ndarray(), out: ti.types.ndarray(), s: ti.types.ndarray()):
        for i in range(a.shape[0]):
            A = a[i]
            B = A @ A.transpose() @ A
            v = B @ ti.Vector([1.0, 2.0, 3.0])
            C = (B @ A) @ (A @ B) - A @ B @ A
            N = ti.Matrix([[A[0, 0], A[0, 1], A[0, 2]], [A[1, 0], A[1, 1], A[1, 2]]])     # 2×3
            P = N.transpose() @ (N @ A.transpose())                                      # 3×2 @ 2×3
            K = ti.Matrix([[1, 2, 3], [4, 5, 6], [7, 8, i]]) @ ti.Vector([i, 2, 3])      # integers
            T = ti.Matrix([[A[0, 0], A[0, 1]], [A[1, 0], A[1, 1]]])                       # 2×2
            Z = ti.Matrix.zero(float, 3, 3) + ti.Matrix.identity(float, 3) + ti.Vector.zero(float, 3).outer_product(v)
            out[i] = C + v.outer_product(v) @ B + a[i] @ a[i].transpose() + P + (v @ A).outer_product(v) \
                + A.inverse() + a[i].inverse().transpose() @ Z
            s[i] = v.dot(v) + A.norm() + B.norm_sqr() + C.sum() + v.norm() + v.sum() + v.norm(1e-3) \
                + N.sum() + K.sum() + (K * 2).dot(K) + A.determinant() + T.determinant() + T.inverse().sum()
    return matrix_ops_kernel


def _counted(calls, name, operation, *args, **kwargs):
    calls.append(name)
    return operation(*args, **kwargs)


def test_direct_matrix_operations_compute_taichi_own_bits(monkeypatch):
    """The same kernel compiled with tissue.frontend's direct operations and with Taichi's own
    pyfuncs gives the same bits; and the direct build handed only the vector @ matrix product to
    Taichi's own (the others were built directly)."""
    from taichi.lang import matrix_ops

    backend.init("cpu")
    frontend.install()
    a = ti.ndarray(ti.types.matrix(3, 3, ti.f64), 64)
    a.from_numpy(np.random.default_rng(0).normal(size=(64, 3, 3)))

    def run():
        out, s = ti.ndarray(ti.types.matrix(3, 3, ti.f64), 64), ti.ndarray(ti.f64, 64)
        _matrix_kernel()(a, out, s)
        return out.to_numpy(), s.to_numpy()

    handed_over = []
    with monkeypatch.context() as patch:
        for name, original in frontend._original_ops.items():
            patch.setitem(frontend._original_ops, name, functools.partial(_counted, handed_over, name, original))
        direct = run()
    with monkeypatch.context() as patch:
        for name, original in frontend._original_ops.items():
            patch.setattr(matrix_ops, name, original)
        taichi_own = run()
    assert handed_over == ["matmul"]
    for mine, theirs in zip(direct, taichi_own):
        assert np.array_equal(mine, theirs)
    assert np.isfinite(direct[0]).all() and np.abs(direct[0]).max() > 1.0
