"""Declarative parameter tables: one field declaration gives the default, the unit, the
meaning, the limits, the validation of the value type, the TOML reader and the docs.

A parameter group is a frozen dataclass whose fields are made with :func:`param`; its
``__post_init__`` calls :func:`validate`. :func:`from_table` reads it from a
:class:`~nanoasm.schema.Table` (unknown keys are rejected with a suggestion), and
:func:`to_table` writes only the values that differ from the defaults::

    @dataclass(frozen=True)
    class Tip:
        radius: float = param(10.0, "nm", "apex radius", positive=True)

        def __post_init__(self) -> None:
            validate(self)
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, TypeVar

from nanoasm.schema import Table, check_number

T = TypeVar("T")

_LIMITS = ("positive", "nonnegative", "lo", "hi")


class ParamError(ValueError):
    """A value-type check that names the offending key (``key``) and the ``problem``."""

    def __init__(self, key: str | None, problem: str):
        self.key = key
        self.problem = problem
        super().__init__(f"{key}: {problem}" if key else problem)


def param(default: Any, unit: str, doc: str, *, source: str = "", required: bool = False,
          positive: bool = False, nonnegative: bool = False, lo: float | None = None,
          hi: float | None = None) -> Any:
    """A dataclass field carrying its unit, meaning, seed source and limits.

    The kind follows the default: ``int`` (an integer), ``float`` (a number) or a tuple
    of numbers (a fixed-length array, limits apply to each entry). ``required`` means
    the key must be present whenever its table is (the scene's fixed ``[drift]`` and
    ``[noise]`` keys).
    """
    meta = {"unit": unit, "doc": doc, "source": source, "required": required,
            "positive": positive, "nonnegative": nonnegative, "lo": lo, "hi": hi}
    return dataclasses.field(default=default, metadata=meta)


def _limits(f: dataclasses.Field) -> dict:
    return {k: f.metadata[k] for k in _LIMITS if f.metadata[k] not in (None, False)}


def _components(n: int) -> tuple[str, ...]:
    return ("x", "y", "z")[:n] if n <= 3 else tuple(f"[{i}]" for i in range(1, n + 1))


def _check_field(f: dataclasses.Field, value: Any, fail: Callable[[str], None]) -> Any:
    default = f.default
    if isinstance(default, tuple):
        if not isinstance(value, (tuple, list)) or len(value) != len(default):
            fail(f"must be {len(default)} numbers, got {value!r}")
        return tuple(check_number(v, lambda p, c=c: fail(f"{c} {p}"), **_limits(f))
                     for v, c in zip(value, _components(len(default))))
    if isinstance(default, bool):
        raise TypeError("boolean parameters are not supported")
    return check_number(value, fail, integer=isinstance(default, int), **_limits(f))


def validate(obj: Any) -> None:
    """Check and normalise every field of a parameter dataclass (call in ``__post_init__``).

    Numbers become ``float`` (``int`` for integer fields), arrays become tuples; a bad
    value raises :class:`ParamError` naming the field.
    """
    for f in dataclasses.fields(obj):
        def fail(problem: str, name: str = f.name) -> None:
            raise ParamError(name, problem)

        object.__setattr__(obj, f.name, _check_field(f, getattr(obj, f.name), fail))


def from_table(cls: type[T], t: Table) -> T:
    """Read a parameter group from one table; errors name the file and the key path."""
    fields = dataclasses.fields(cls)
    t.check_keys(required=[f.name for f in fields if f.metadata["required"]],
                 optional=[f.name for f in fields])
    kwargs = {}
    for f in fields:
        if f.name in t:
            kwargs[f.name] = _check_field(f, t.data[f.name], lambda p, n=f.name: t.fail(n, p))
    try:
        return cls(**kwargs)
    except ParamError as e:  # a constraint between keys, found by the class itself
        raise t.error(e.key, e.problem) from None


def to_table(obj: Any) -> dict:
    """The fields that differ from their defaults, as TOML-ready values.

    A table that is written at all gets its required keys too, so it reads back.
    """
    fields = dataclasses.fields(obj)
    changed = {f.name for f in fields if getattr(obj, f.name) != f.default}
    if changed:
        changed |= {f.name for f in fields if f.metadata["required"]}
    out = {}
    for f in fields:
        if f.name in changed:
            value = getattr(obj, f.name)
            out[f.name] = list(value) if isinstance(value, tuple) else value
    return out


def _show(value: Any) -> str:
    if isinstance(value, tuple):
        return "[" + ", ".join(_show(v) for v in value) + "]"
    return f"{value:g}" if isinstance(value, float) else str(value)


def markdown_rows(cls: type) -> list[str]:
    """Markdown table rows ``| key | default | unit | meaning | source |`` for one group."""
    rows = []
    for f in dataclasses.fields(cls):
        m = f.metadata
        req = " (required)" if m["required"] else ""
        rows.append(f"| `{f.name}`{req} | {_show(f.default)} | {m['unit']} | {m['doc']} | {m['source']} |")
    return rows
