"""Declared parameters and the one check of a number, with the standard library alone.

A parameter group is a frozen dataclass whose fields are made with :func:`param`, each
with its default, unit, meaning and limits; its ``__post_init__`` calls
:func:`validate`, which checks and normalises every such field and raises
:class:`ParamError` (a ``ValueError``) naming the field::

    @dataclass(frozen=True)
    class Tip:
        radius: float = param(10.0, "nm", "apex radius", positive=True)

        def __post_init__(self) -> None:
            validate(self)

:func:`check_number` is the project's one check of a scalar: :func:`validate` uses it,
:class:`nanoasm.schema.Table` uses it for files, and :func:`number` for a function's
arguments. This module imports nothing of the project, so every package may use it
(``nanoasm.drift`` imports nothing else of the project); reading and writing groups as
TOML tables is :mod:`nanoasm.world.param_spec`.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import numbers
from collections.abc import Callable, Iterable
from typing import Any, NoReturn

_LIMITS = ("positive", "nonnegative", "lo", "hi")


class ParamError(ValueError):
    """A value-type check that names the offending key (``key``) and the ``problem``."""

    def __init__(self, key: str | None, problem: str):
        self.key = key
        self.problem = problem
        super().__init__(f"{key}: {problem}" if key else problem)


def type_name(value: Any) -> str:
    """A user-facing name for the type of a parsed TOML/JSON value."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, int):
        return "an integer"
    if isinstance(value, float):
        return "a number"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, (list, tuple)):
        return "an array"
    if isinstance(value, dict):
        return "a table"
    return type(value).__name__


def show_value(value: Any) -> str:
    """``value`` as an error message quotes it: strings shortened, arrays and tables by type."""
    if isinstance(value, str):
        text = value if len(value) <= 40 else value[:37] + "..."
        return repr(text)
    if isinstance(value, float):
        return repr(float(value))
    if isinstance(value, (list, dict)):
        return type_name(value)
    return str(value)


def check_number(
    value: Any,
    fail: Callable[[str], NoReturn],
    *,
    positive: bool = False,
    nonnegative: bool = False,
    lo: float | None = None,
    hi: float | None = None,
    integer: bool = False,
) -> float | int:
    """Check one real scalar (numpy scalars too; booleans are not numbers) and return it
    as ``float``, or ``int`` when ``integer``; ``fail(problem)`` raises the caller's
    located error."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        want = "an integer" if integer else "a number"
        fail(f"must be {want}, got {type_name(value)} {show_value(value)}".rstrip())
    if integer and not isinstance(value, numbers.Integral):
        fail(f"must be an integer, got {show_value(value)}")
    if isinstance(value, numbers.Integral) and not integer and abs(value) > 2**1023:
        fail(f"must be finite, got a number too large for a float ({str(value)[:12]}...)")
    if integer and abs(value) >= 2**63:
        fail("must be an integer below 2**63")
    if not math.isfinite(value):
        fail(f"must be finite, got {show_value(value)}")
    if positive and not value > 0:
        fail(f"must be positive, got {show_value(value)}")
    if nonnegative and value < 0:
        fail(f"must not be negative, got {show_value(value)}")
    if lo is not None and value < lo:
        fail(f"must be at least {lo:g}, got {show_value(value)}")
    if hi is not None and value > hi:
        fail(f"must be at most {hi:g}, got {show_value(value)}")
    return int(value) if integer else float(value)


def number(name: str, value: Any, **limits: Any) -> float | int:
    """``value`` checked by :func:`check_number` with ``limits``; a bad one raises
    :class:`ParamError` naming ``name`` (for a function's arguments)."""
    def fail(problem: str) -> NoReturn:
        raise ParamError(name, problem)

    return check_number(value, fail, **limits)


def param(default: Any, unit: str, doc: str, *, source: str = "", required: bool = False,
          optional: bool = False, positive: bool = False, nonnegative: bool = False,
          lo: float | None = None, hi: float | None = None,
          choices: Iterable[str] | None = None) -> Any:
    """A dataclass field carrying its unit, meaning, seed source and limits.

    The kind follows the default: ``int`` (an integer), ``float`` (a number), a tuple
    of numbers (a fixed-length array, limits apply to each entry), ``str`` (a string,
    one of ``choices`` when given) or an enum member (a member of that enum, or its
    value). ``optional`` lets the value be None as well (a default of None makes a
    number). ``required`` means the key must be present whenever its table is (the
    scene's fixed ``[drift]`` and ``[noise]`` keys).
    """
    if isinstance(default, bool):
        raise TypeError("boolean parameters are not supported")
    if default is None and not optional:
        raise TypeError("a parameter whose default is None must be optional")
    meta = {"param": True, "unit": unit, "doc": doc, "source": source, "required": required,
            "optional": optional, "positive": positive, "nonnegative": nonnegative, "lo": lo, "hi": hi,
            "choices": None if choices is None else tuple(choices)}
    return dataclasses.field(default=default, metadata=meta)


def is_param(f: dataclasses.Field) -> bool:
    """Whether field ``f`` was made with :func:`param`."""
    return bool(f.metadata.get("param"))


def _limits(f: dataclasses.Field) -> dict:
    m = f.metadata          # not "in (None, False)": a limit of 0.0 equals False
    return {k: m[k] for k in _LIMITS if m[k] is not None and m[k] is not False}


def _components(n: int) -> tuple[str, ...]:
    return ("x", "y", "z")[:n] if n <= 3 else tuple(f"[{i}]" for i in range(1, n + 1))


def _one_of(names: Iterable[str], value: Any) -> str:
    return f"must be one of {', '.join(map(repr, names))}, got {show_value(value)}"


def check_field(f: dataclasses.Field, value: Any, fail: Callable[[str], NoReturn]) -> Any:
    """``value`` checked and normalised as field ``f`` (made with :func:`param`) declares."""
    default, meta = f.default, f.metadata
    if value is None and meta["optional"]:
        return None
    if isinstance(default, enum.Enum):
        kind = type(default)
        try:
            return kind(value)
        except (ValueError, TypeError):
            fail(_one_of((m.value for m in kind), value))
    if isinstance(default, str):
        if not isinstance(value, str):
            fail(f"must be a string, got {type_name(value)} {show_value(value)}".rstrip())
        if meta["choices"] is not None and value not in meta["choices"]:
            fail(_one_of(meta["choices"], value))
        return value
    if isinstance(default, tuple):
        if not isinstance(value, (tuple, list)) or len(value) != len(default):
            fail(f"must be {len(default)} numbers, got {value!r}")
        return tuple(check_number(v, lambda p, c=c: fail(f"{c} {p}"), **_limits(f))
                     for v, c in zip(value, _components(len(default))))
    return check_number(value, fail, integer=isinstance(default, int), **_limits(f))


def validate(obj: Any) -> None:
    """Check and normalise every :func:`param` field of a dataclass (call in ``__post_init__``).

    Numbers become ``float`` (``int`` for integer fields), arrays become tuples, enum
    values become members; a bad value raises :class:`ParamError` naming the field.
    Fields not made with :func:`param` are left to the class.
    """
    for f in dataclasses.fields(obj):
        if not is_param(f):
            continue

        def fail(problem: str, name: str = f.name) -> NoReturn:
            raise ParamError(name, problem)

        object.__setattr__(obj, f.name, check_field(f, getattr(obj, f.name), fail))
