"""tissue.frontend's memoised source positions and source reads give Taichi exactly what it computed itself."""

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
        compared.append(memo == frontend._original_pos_info(ctx, node))
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


def test_memoised_fill_equals_textwrap():
    import textwrap

    for line in ("\tif a:\t# tab", "    x = 1", ""):
        assert frontend._fill(line, tabsize=4, width=9999) == textwrap.fill(line, tabsize=4, width=9999)
