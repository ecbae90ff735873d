"""Taichi's Python front end, made cheap where it repeats: memoised source reads, source positions,
source line filling, and the decorators' class check.

Taichi 1.7 turns a kernel's Python source into its IR at the kernel's first launch in every
process, even when the compiled kernel then comes from the offline cache; and a `ti.func` is read
and transformed again at every call site it is inlined into (the serial step kernel inlines its
CG and multigrid hundreds of times). Most of that time went to two pure functions of the source:

- `ASTTransformerContext.get_pos_info`, the "File …, line …" text with a caret line, wrapped by
  `textwrap` to 80 columns, built for every name and statement for Taichi's error messages;
- `inspect.getsourcelines` / `getsourcefile`, which tokenise the module to find a function.

Then, at each call site again, every source line of the function goes through `textwrap.fill`
(to expand tabs: a pure function of the line). And when a module is imported, every `@ti.kernel` /
`@ti.func` asks whether it is written in a class body through `inspect.getframeinfo`, which looks
the module up among all loaded modules (`inspect.getmodule`) to read one source line: ~2 ms per
decorator, some 230 of them on a scene's imports. `_inside_class` reads that line from
`linecache` directly, as `getframeinfo` ends up doing.

`install()` memoises the first three by their inputs and replaces the class check. Taichi receives
the same strings and answers as before (tests/test_frontend.py compares them with its own), so its
messages and its offline-cache keys do not change. `tissue.backend` installs it when imported,
before any of tissue's modules defines a kernel.
"""

from __future__ import annotations

import functools
import linecache
import sys
import textwrap
import types

from taichi.lang import kernel_impl
from taichi.lang.ast import ast_transformer_utils

_original_pos_info = ast_transformer_utils.ASTTransformerContext.get_pos_info
_original_sourcelines = kernel_impl.getsourcelines
_original_sourcefile = kernel_impl.getsourcefile
_original_inside_class = kernel_impl._inside_class
_pos_info: dict[tuple, str] = {}


def _position_key(ctx, node) -> tuple:
    """Everything `get_pos_info` reads: the node's span and the source lines it prints (a loop,
    branch or definition up to its body's first line, as it does)."""
    if type(node).__name__ in ("For", "While", "FunctionDef", "If"):
        end = max(node.body[0].lineno - 1, node.lineno)
    else:
        end = node.end_lineno
    return (ctx.file, ctx.lineno_offset, ctx.indent, ctx.func.func.__name__, type(node).__name__,
            node.lineno, node.end_lineno, node.col_offset, node.end_col_offset, tuple(ctx.src[node.lineno - 1:end]))


def _get_pos_info(ctx, node) -> str:
    key = _position_key(ctx, node)
    text = _pos_info.get(key)
    if text is None:
        text = _pos_info[key] = _original_pos_info(ctx, node)
    return text


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


def install() -> None:
    """Memoise the front end's source reads, positions and line filling, and replace the
    decorators' class check (idempotent)."""
    ast_transformer_utils.ASTTransformerContext.get_pos_info = _get_pos_info
    kernel_impl.getsourcelines = _getsourcelines_list
    kernel_impl.getsourcefile = functools.cache(_original_sourcefile)
    # kernel_impl's own name for the textwrap module: fill memoised, the rest as is.
    kernel_impl.textwrap = types.SimpleNamespace(fill=_fill, dedent=textwrap.dedent)
    kernel_impl._inside_class = _inside_class
