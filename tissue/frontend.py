"""Taichi's Python front end, made cheap where it repeats: memoised source reads and source positions.

Taichi 1.7 turns a kernel's Python source into its IR at the kernel's first launch in every
process, even when the compiled kernel then comes from the offline cache; and a `ti.func` is read
and transformed again at every call site it is inlined into (the serial step kernel inlines its
CG and multigrid hundreds of times). Most of that time went to two pure functions of the source:

- `ASTTransformerContext.get_pos_info`, the "File …, line …" text with a caret line, wrapped by
  `textwrap` to 80 columns, built for every name and statement for Taichi's error messages;
- `inspect.getsourcelines` / `getsourcefile`, which tokenise the module to find a function.

`install()` memoises both by their inputs. Taichi receives the same strings as before
(tests/test_frontend.py compares them with its own), so its messages and its offline-cache keys
do not change.
"""

from __future__ import annotations

import functools

from taichi.lang import kernel_impl
from taichi.lang.ast import ast_transformer_utils

_original_pos_info = ast_transformer_utils.ASTTransformerContext.get_pos_info
_original_sourcelines = kernel_impl.getsourcelines
_original_sourcefile = kernel_impl.getsourcefile
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


def install() -> None:
    """Memoise the front end's source reads and positions (idempotent)."""
    ast_transformer_utils.ASTTransformerContext.get_pos_info = _get_pos_info
    kernel_impl.getsourcelines = _getsourcelines_list
    kernel_impl.getsourcefile = functools.cache(_original_sourcefile)
