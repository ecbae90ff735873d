"""Taichi's Python front end, made cheap where it repeats: memoised source reads, source positions,
source line filling, and the decorators' class check.

Taichi 1.7 turns a kernel's Python source into its IR at the kernel's first launch in every
process, even when the compiled kernel then comes from the offline cache; and a `ti.func` is read
and transformed again at every call site it is inlined into (the serial step kernel inlines its
CG and multigrid hundreds of times). Most of that time went to two pure functions of the source:

- `ASTTransformerContext.get_pos_info`, the "File …, line …" text with a caret line, wrapped by
  `textwrap` to 80 columns, built for every name and statement for Taichi's error messages (where
  a node is new to the memo, its lines go through one `_Wrapper`: a line that fits in 80 columns
  needs no wrapping, only its trailing spaces dropped);
- `inspect.getsourcelines` / `getsourcefile`, which tokenise the module to find a function.

Then, at each call site again, every source line of the function goes through `textwrap.fill`
(to expand tabs: a pure function of the line). And when a module is imported, every `@ti.kernel` /
`@ti.func` asks whether it is written in a class body through `inspect.getframeinfo`, which looks
the module up among all loaded modules (`inspect.getmodule`) to read one source line, for every one
of the hundreds of decorators on a scene's imports: a visible part of its start-up
(bench.startup). `_inside_class` reads that line from `linecache` directly, as `getframeinfo`
ends up doing.

`install()` memoises the first three by their inputs, gives `get_pos_info` the fast wrapper and
replaces the class check. Taichi receives
the same strings and answers as before (tests/test_frontend.py compares them with its own), so its
messages do not change. `tissue.backend` installs it when imported, before any of tissue's modules
defines a kernel.

The small-matrix operations (`A @ B`, `A @ v`, `.transpose()`, `.outer_product()`, `.sum()`,
`.dot()`, `.norm_sqr()`, `.norm()`, `.determinant()`, `.inverse()`, `ti.Matrix.identity`, `.zero`)
are Taichi "pyfuncs": Python with static loops, transformed
again at every use, one AST node at a time: a 3×3 product unrolls 27 statements, and the step
kernel made 30 of them (16,000 of its 38,000 nodes). `install()` builds them instead directly from
the operands' entries, the same scalar arithmetic in the same order as Taichi's own (its `0 · a₀₀
b₀₀` start of every dot product included): the compiled code computes the same bits
(tests/test_frontend.py compares the two), the front end does a fifth of the work. Anything else
(other shapes, Python-scope matrices) goes to Taichi's own.
"""

from __future__ import annotations

import functools
import linecache
import sys
import textwrap
import types

from taichi.lang import impl, kernel_impl, matrix_ops, ops
from taichi.lang.ast import ast_transformer_utils
from taichi.lang.expr import Expr
from taichi.lang.matrix import make_matrix

_original_pos_info = ast_transformer_utils.ASTTransformerContext.get_pos_info
_original_sourcelines = kernel_impl.getsourcelines
_original_sourcefile = kernel_impl.getsourcefile
_original_inside_class = kernel_impl._inside_class
_original_ops = {name: getattr(matrix_ops, name)
                 for name in ("matmul", "transpose", "outer_product", "sum", "dot", "norm_sqr", "norm", "determinant",
                              "inverse", "_identity_matrix", "_filled_matrix", "_filled_vector")}
_pos_info: dict[tuple, str] = {}


def _position_key(ctx, node) -> tuple:
    """What `get_pos_info`'s text is a function of: the node's kind and span in the source of the
    Python function being transformed (whose lines, read once by `_getsourcelines`, do not change)
    and where that source sits (line offset, indentation)."""
    return (ctx.func.func, ctx.lineno_offset, ctx.indent, type(node).__name__, node.lineno, node.end_lineno,
            node.col_offset, node.end_col_offset)


def _get_pos_info(ctx, node) -> str:
    key = _position_key(ctx, node)
    text = _pos_info.get(key)
    if text is None:
        text = _pos_info[key] = _original_pos_info(ctx, node)
    return text


class _Wrapper(textwrap.TextWrapper):
    """TextWrapper, with the answer for a line of printable ASCII that fits in `width` given
    directly: its one line, less the trailing spaces (none where it is blank), as
    `TextWrapper.wrap` makes it (no tab or other whitespace to convert, nothing to break). Any
    other line is wrapped by TextWrapper once: a long source line comes back for each of its
    nodes."""

    def __init__(self, width: int):
        super().__init__(width=width)
        self._wrapped: dict[str, tuple[str, ...]] = {}

    def wrap(self, text: str) -> list[str]:
        if len(text) <= self.width and text.isascii() and text.isprintable():
            line = text.rstrip(" ")
            return [line] if line else []
        lines = self._wrapped.get(text)
        if lines is None:
            lines = self._wrapped[text] = tuple(super().wrap(text))
        return list(lines)


@functools.cache
def _wrapper(width: int = 70) -> _Wrapper:
    """`get_pos_info`'s `TextWrapper(width=80)`, made once: wrapping changes no state of the wrapper."""
    return _Wrapper(width=width)


@functools.cache
def _getsourcelines(function):
    lines, start = _original_sourcelines(function)
    return tuple(lines), start


def _getsourcelines_list(function):
    lines, start = _getsourcelines(function)
    return list(lines), start


@functools.cache
def _fill(text: str, **options) -> str:
    return textwrap.fill(text, **options)


def _inside_class(level_of_class_stackframe: int) -> bool:
    """Taichi's check (kernel_impl._inside_class): is the line `level` frames up a class statement
    (or a data_oriented decorator)? The same line, read without inspect's module search."""
    try:
        frame = sys._getframe(level_of_class_stackframe)
        line = linecache.getline(frame.f_code.co_filename, frame.f_lineno, frame.f_globals).strip()
    except ValueError:           # no frame that far up
        return False
    return any(pattern.match(line) for pattern in kernel_impl._KERNEL_CLASS_STACKFRAME_STMT_RES)


# ---- small-matrix operations built directly (see the module's docstring) -------------------------


def _tensor(x, dims: int) -> bool:
    """A Taichi-scope matrix (dims 2) or vector (dims 1) expression."""
    return isinstance(x, Expr) and x.is_tensor() and len(x.get_shape()) == dims


def _entries(x) -> list:
    """x's entries as expressions, x first copied to a local as a ti.func argument is (so each entry
    reads the same value however often it is used)."""
    x = impl.expr_init(x)
    shape = x.get_shape()
    if len(shape) == 1:
        return [impl.subscript(None, x, i) for i in range(shape[0])]
    return [[impl.subscript(None, x, i, j) for j in range(shape[1])] for i in range(shape[0])]


def _dot(xs, ys, zero):
    """Taichi's accumulation in _matmul_helper: ((zero + x₀y₀) + x₁y₁) + …"""
    total = zero
    for x, y in zip(xs, ys):
        total = total + x * y
    return total


def _folded(values):
    """Taichi's _reduce with add: ((v₀ + v₁) + v₂) + …"""
    total = values[0]
    for v in values[1:]:
        total = total + v
    return total


def _direct(name, build, applies):
    """Taichi's operation `name`, built by `build` where `applies` to its operands inside a kernel."""
    def operation(*args, **kwargs):
        if impl.inside_kernel() and not kwargs and applies(*args):
            return build(*args)
        return _original_ops[name](*args, **kwargs)

    # Taichi's attributes of its own (a ti.func's marks, read where a kernel calls it) and its name.
    return functools.update_wrapper(operation, _original_ops[name])


def _matmul(a, b):
    x, y = _entries(a), _entries(b)
    if _tensor(b, 1):
        zero = impl.expr_init(x[0][0] * y[0] * 0)           # Taichi's "for correct return type" zero
        return impl.expr_init(make_matrix([_dot(row, y, zero) for row in x]))
    zero = impl.expr_init(x[0][0] * y[0][0] * 0)
    columns = list(zip(*y))
    return impl.expr_init(make_matrix([[_dot(row, column, zero) for column in columns] for row in x]))


def _matmul_applies(a, b) -> bool:
    return _tensor(a, 2) and (_tensor(b, 2) or _tensor(b, 1)) and a.get_shape()[1] == b.get_shape()[0]


def _norm_sqr(x):
    return _folded([v * v for v in _flat(x)])


def _flat(x) -> list:
    entries = _entries(x)
    return entries if len(x.get_shape()) == 1 else [v for row in entries for v in row]


def _square(a) -> bool:
    return _tensor(a, 2) and a.get_shape() in ((2, 2), (3, 3))


def _determinant_of(x):
    """Taichi's formula (matrix_ops.determinant) on the entries x of a 2×2 or 3×3 matrix."""
    if len(x) == 2:
        return x[0][0] * x[1][1] - x[0][1] * x[1][0]
    return (x[0][0] * (x[1][1] * x[2][2] - x[2][1] * x[1][2])
            - x[1][0] * (x[0][1] * x[2][2] - x[2][1] * x[0][2])
            + x[2][0] * (x[0][1] * x[1][2] - x[1][1] * x[0][2]))


def _inverse(a):
    """Taichi's (matrix_ops.inverse): 1 / det times the transposed cofactors, as it writes them."""
    x = _entries(a)
    inverse_determinant = impl.expr_init(1.0 / _determinant_of(x))
    if len(x) == 2:
        return inverse_determinant * make_matrix([[x[1][1], -x[0][1]], [-x[1][0], x[0][0]]])
    e = lambda i, j: x[i % 3][j % 3]       # noqa: E731  (Taichi's E)
    return inverse_determinant * make_matrix([[e(i + 1, j + 1) * e(i + 2, j + 2) - e(i + 2, j + 1) * e(i + 1, j + 2)
                                               for i in range(3)] for j in range(3)])


_DIRECT = {
    "matmul": (_matmul, _matmul_applies),
    "transpose": (lambda a: make_matrix([list(column) for column in zip(*_entries(a))]), lambda a: _tensor(a, 2)),
    "outer_product": (lambda u, v: make_matrix([[p * q for q in _entries(v)] for p in _entries(u)]),
                      lambda u, v: _tensor(u, 1) and _tensor(v, 1)),
    "sum": (lambda a: _folded(_flat(a)), lambda a: _tensor(a, 1) or _tensor(a, 2)),
    "dot": (lambda u, v: _folded([p * q for p, q in zip(_entries(u), _entries(v))]),
            lambda u, v: _tensor(u, 1) and _tensor(v, 1) and u.get_shape() == v.get_shape()),
    "norm_sqr": (_norm_sqr, lambda a: _tensor(a, 1) or _tensor(a, 2)),
    "norm": (lambda a, eps=0.0: ops.sqrt(_norm_sqr(a) + eps), lambda a, eps=0.0: _tensor(a, 1) or _tensor(a, 2)),
    "determinant": (lambda a: _determinant_of(_entries(a)), _square),
    "inverse": (_inverse, _square),
    # The constructors take compile-time arguments only: Taichi's own comprehension, without its transform.
    "_identity_matrix": (lambda n, dtype: make_matrix([[i == j for j in range(n)] for i in range(n)], dtype),
                         lambda n, dtype: True),
    "_filled_matrix": (lambda n, m, dtype, val: make_matrix([[val for _ in range(m)] for _ in range(n)], dtype),
                       lambda n, m, dtype, val: True),
    "_filled_vector": (lambda n, dtype, val: make_matrix([val for _ in range(n)], dtype), lambda n, dtype, val: True),
}


def install() -> None:
    """Memoise the front end's source reads, positions and line filling, replace the
    decorators' class check, and build the small-matrix operations directly (idempotent)."""
    ast_transformer_utils.ASTTransformerContext.get_pos_info = _get_pos_info
    ast_transformer_utils.TextWrapper = _wrapper          # the module's own name for the class
    kernel_impl.getsourcelines = _getsourcelines_list
    kernel_impl.getsourcefile = functools.cache(_original_sourcefile)
    # kernel_impl's own name for the textwrap module: fill memoised, the rest as is.
    kernel_impl.textwrap = types.SimpleNamespace(fill=_fill, dedent=textwrap.dedent)
    kernel_impl._inside_class = _inside_class
    for name, (build, applies) in _DIRECT.items():
        setattr(matrix_ops, name, _direct(name, build, applies))
