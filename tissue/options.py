"""Typed option groups: dataclasses whose fields are checked by their annotations, set from text.

Scenes and their parts (`tissue.scene`) are `Options`: plain dataclasses of typed fields. This
module gives them three things, driven only by the annotations:

  * strict construction: an unknown keyword is refused with a suggestion
    (`SoftBody(yung=1)` -> "SoftBody.yung: unknown field; did you mean 'young'?");
  * `validate(options)`: every field's type (recursively), then each group's own `check()` for
    ranges, with errors naming the dotted field (`liver.poisson: ...`);
  * `apply_overrides(options, ["liver.young=5e3", ...])`: text parsed by the target field's type
    (float, int, bool, str, Literal choices, Optional, tuples, Path), nested fields by dots.

Supported annotations: float, int, bool, str, pathlib.Path, Literal[...], X | None, tuple[X, ...],
tuple[X, Y, Z], and nested Options.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import types
import typing
from functools import lru_cache
from pathlib import Path
from typing import Any, Literal, Union

from .errors import TissueError


class _Invalid(Exception):
    """Raised by `Options.check()` through `require`; `validate` prefixes the dotted path."""

    def __init__(self, field: str, message: str):
        super().__init__(field, message)
        self.field, self.message = field, message


def require(condition: bool, field: str, message: str) -> None:
    """In a `check()` method: fail with `message` about `field` unless `condition`."""
    if not condition:
        raise _Invalid(field, message)


def suggestion(name: str, candidates) -> str:
    """"; did you mean 'x'?" for the closest candidate, else the list of candidates."""
    candidates = list(candidates)
    close = difflib.get_close_matches(name, candidates, n=1, cutoff=0.6)
    if close:
        return f"; did you mean {close[0]!r}?"
    return f"; expected one of {', '.join(candidates)}" if candidates else ""


class _StrictMeta(type):
    """Refuses unknown keyword arguments with a one-line suggestion, before the dataclass sees them."""

    def __call__(cls, *args, **kwargs):
        if dataclasses.is_dataclass(cls):
            known = [f.name for f in dataclasses.fields(cls) if f.init]
            for name in kwargs:
                if name not in known:
                    raise TissueError(f"{cls.__name__}.{name}: unknown field{suggestion(name, known)}")
        return super().__call__(*args, **kwargs)


class Options(metaclass=_StrictMeta):
    """Base of every option group. Subclasses are @dataclass'es and may define `check()`."""

    def check(self) -> None:
        """Range checks of this group's own fields (types are already checked); use `require`."""


def is_options(value) -> bool:
    return isinstance(value, Options) and dataclasses.is_dataclass(value)


@lru_cache(maxsize=None)
def field_types(cls) -> dict[str, Any]:
    """The resolved annotation of each dataclass field of `cls`."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


# ---- type checks ---------------------------------------------------------------------------------


def _describe(tp) -> str:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is float:
        return "a number"
    if tp is int:
        return "an integer"
    if tp is bool:
        return "true or false"
    if tp is str:
        return "a string"
    if tp is Path:
        return "a path"
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    if origin in (Union, types.UnionType):
        return " or ".join("none" if a is type(None) else _describe(a) for a in args)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a comma-separated list of {_plural(args[0])}"
        if not args:
            return "an empty list"
        return f"{len(args)} comma-separated values ({', '.join(_describe(a) for a in args)})"
    if isinstance(tp, type) and issubclass(tp, Options):
        return f"a {tp.__name__}"
    return getattr(tp, "__name__", str(tp))


def _plural(tp) -> str:
    return {float: "numbers", int: "integers", bool: "booleans", str: "strings", Path: "paths"}.get(
        tp, _describe(tp))


def _type_error(where: str, tp, value) -> TissueError:
    return TissueError(f"{where}: expected {_describe(tp)}, got {value!r}")


def check_type(value, tp, where: str) -> None:
    """Raise a TissueError naming `where` unless `value` fits the annotation `tp`."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (Union, types.UnionType):
        if value is None and type(None) in args:
            return
        for arg in args:
            if arg is type(None):
                continue
            try:
                check_type(value, arg, where)
                return
            except TissueError:
                pass
        raise _type_error(where, tp, value)
    if origin is Literal:
        if value not in args:
            raise TissueError(f"{where}: unknown value {value!r}"
                              f"{suggestion(str(value), [str(a) for a in args])}")
        return
    if origin is tuple:
        if not isinstance(value, (tuple, list)):
            raise _type_error(where, tp, value)
        if len(args) == 2 and args[1] is Ellipsis:
            items = [(v, args[0]) for v in value]
        else:
            if len(value) != len(args):
                raise TissueError(f"{where}: expected {_describe(tp)}, got {len(value)} values {tuple(value)!r}")
            items = list(zip(value, args))
        for i, (v, t) in enumerate(items):
            check_type(v, t, f"{where}[{i}]")
        return
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _type_error(where, tp, value)
        if not math.isfinite(value):
            raise TissueError(f"{where}: must be a finite number, got {value!r}")
        return
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise _type_error(where, tp, value)
        return
    if tp is bool:
        if not isinstance(value, bool):
            raise _type_error(where, tp, value)
        return
    if tp is str:
        if not isinstance(value, str):
            raise _type_error(where, tp, value)
        return
    if tp is Path:
        if not isinstance(value, (str, Path)):
            raise _type_error(where, tp, value)
        return
    if isinstance(tp, type) and issubclass(tp, Options):
        if not isinstance(value, tp):
            raise _type_error(where, tp, value)
        return
    if tp is Any:
        return
    raise TissueError(f"{where}: unsupported annotation {tp!r} (use float, int, bool, str, Path, "
                      "Literal, Optional, tuple or an Options group)")


def validate(options: Options, path: str = "") -> Options:
    """Check every field of `options` (types, then ranges), recursively; returns `options`."""
    for name, tp in field_types(type(options)).items():
        value = getattr(options, name)
        check_type(value, tp, path + name)
        if is_options(value):
            validate(value, f"{path}{name}.")
    try:
        options.check()
    except _Invalid as bad:
        raise TissueError(f"{path}{bad.field}: {bad.message}") from None
    return options


# ---- text -> values --------------------------------------------------------------------------

_TRUE = {"true", "yes", "on", "1"}
_FALSE = {"false", "no", "off", "0"}
_NONE = {"none", "null", ""}


def parse_value(text: str, tp, where: str):
    """The value of annotation `tp` written as `text` (as on a command line)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    text = text.strip()
    if origin in (Union, types.UnionType):
        if text.lower() in _NONE and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return parse_value(text, arg, where)
            except TissueError as err:
                errors.append(err)
        raise errors[0] if len(errors) == 1 else _type_error(where, tp, text)
    if origin is Literal:
        for choice in args:
            if text == str(choice):
                return choice
        raise TissueError(f"{where}: unknown value {text!r}{suggestion(text, [str(a) for a in args])}")
    if origin is tuple:
        inner = text
        if len(inner) >= 2 and inner[0] + inner[-1] in ("()", "[]"):
            inner = inner[1:-1]
        parts = [p for p in (s.strip() for s in inner.split(","))] if inner.strip() else []
        if parts and parts[-1] == "":  # a trailing comma: "3," is a one-element tuple
            parts = parts[:-1]
        if len(args) == 2 and args[1] is Ellipsis:
            element_types = [args[0]] * len(parts)
        else:
            if len(parts) != len(args):
                raise TissueError(f"{where}: expected {_describe(tp)}, got {text!r}")
            element_types = list(args)
        return tuple(parse_value(p, t, f"{where}[{i}]") for i, (p, t) in enumerate(zip(parts, element_types)))
    if tp is float:
        try:
            return float(text)
        except ValueError:
            raise _type_error(where, tp, text) from None
    if tp is int:
        try:
            return int(text)
        except ValueError:
            try:
                number = float(text)
            except ValueError:
                number = math.nan
            if math.isfinite(number) and number.is_integer():
                return int(number)
            raise _type_error(where, tp, text) from None
    if tp is bool:
        if text.lower() in _TRUE:
            return True
        if text.lower() in _FALSE:
            return False
        raise _type_error(where, tp, text)
    if tp is str:
        if len(text) >= 2 and text[0] == text[-1] and text[0] in "'\"":
            return text[1:-1]
        return text
    if tp is Path:
        return Path(text)
    if isinstance(tp, type) and issubclass(tp, Options):
        names = ", ".join(field_types(tp))
        raise TissueError(f"{where}: is a group of fields ({names}); set one of them, e.g. "
                          f"{where}.{next(iter(field_types(tp)))}=...")
    raise TissueError(f"{where}: cannot be set from text (annotation {tp!r})")


def _set(options: Options, parts: list[str], text: str, where: str) -> Options:
    name = parts[0]
    types_ = field_types(type(options))
    settable = [f.name for f in dataclasses.fields(options) if f.init]
    if name not in settable:
        raise TissueError(f"{where}{name}: unknown field{suggestion(name, settable)}")
    tp = types_[name]
    if len(parts) > 1:
        child = getattr(options, name)
        if not is_options(child):
            raise TissueError(f"{where}{name}: is a single value ({_describe(tp)}); "
                              f"it has no field {parts[1]!r}")
        return dataclasses.replace(options, **{name: _set(child, parts[1:], text, f"{where}{name}.")})
    value = parse_value(text, tp, where + name)
    return dataclasses.replace(options, **{name: value})


def apply_overrides(options: Options, assignments) -> Options:
    """A copy of `options` with each "a.b.c=value" applied in order (the value parsed by the
    field's type). Raises a one-line TissueError naming the field on any unknown name or bad value."""
    for assignment in assignments:
        if "=" not in assignment:
            raise TissueError(f"--set {assignment!r}: expected FIELD=VALUE, e.g. liver.young=5e3")
        key, text = assignment.split("=", 1)
        key = key.strip()
        parts = key.split(".")
        if not key or any(not p for p in parts):
            raise TissueError(f"--set {assignment!r}: expected FIELD=VALUE, e.g. liver.young=5e3")
        options = _set(options, parts, text, "")
    return options


def flatten(options: Options, prefix: str = "") -> dict[str, Any]:
    """{"liver.young": 3000.0, ...}: every leaf field by its dotted name (tuples as lists)."""
    out = {}
    for name in field_types(type(options)):
        value = getattr(options, name)
        if is_options(value):
            out.update(flatten(value, f"{prefix}{name}."))
        elif isinstance(value, Path):
            out[prefix + name] = str(value)
        elif isinstance(value, tuple):
            out[prefix + name] = list(value)
        else:
            out[prefix + name] = value
    return out


def format_value(value) -> str:
    """A value as it would be written after --set a.b=."""
    if isinstance(value, (tuple, list)):
        return ",".join(format_value(v) for v in value)
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)
