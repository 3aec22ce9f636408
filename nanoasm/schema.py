"""Validation of parsed TOML/JSON tables, with errors that name the key path.

A :class:`Table` wraps one parsed table and its position in the document; its getters
return checked Python values or raise :class:`~nanoasm.errors.InputError`::

    t = Table(doc, "layout.toml")
    t.check_keys(required={"format", "area"}, optional={"name"})
    w, h = t.pair("area", positive=True)

Array indices in key paths count from 1, as a person counts ``[[target]]`` blocks.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Mapping
from typing import Any

from .errors import InputError
from .param import check_number, show_value, type_name

_MISSING: Any = object()

Point = tuple[float, float]


def _entries(value: list) -> str:
    return f"{len(value)} entry" if len(value) == 1 else f"{len(value)} entries"


class Table:
    """One parsed table of a document, located by ``source`` and ``path``."""

    def __init__(self, data: Any, source: str | None, path: str = ""):
        if not isinstance(data, Mapping):
            raise InputError(source, path or None, f"must be a table, got {type_name(data)}")
        self.data = data
        self.source = source
        self.path = path

    # -- locating -------------------------------------------------------------------
    def key(self, name: str) -> str:
        if not isinstance(name, str) or not name or not name.isprintable() or " " in name:
            name = repr(name)
        return f"{self.path}.{name}" if self.path else name

    def error(self, name: str | None, problem: str) -> InputError:
        return InputError(self.source, self.key(name) if name else (self.path or None), problem)

    def fail(self, name: str | None, problem: str):
        raise self.error(name, problem)

    def __contains__(self, name: str) -> bool:
        return name in self.data

    # -- keys -----------------------------------------------------------------------
    def check_keys(self, required: Iterable[str] = (), optional: Iterable[str] = (), *,
                   context: str = "") -> None:
        """Reject unknown keys (suggesting the nearest allowed one), then missing ones."""
        required = list(required)
        allowed = set(required) | set(optional)
        for k in self.data:
            if not isinstance(k, str) or k in allowed:
                continue
            near = difflib.get_close_matches(k, sorted(allowed), n=1, cutoff=0.6)
            if near:
                hint = f"did you mean {near[0]!r}?"
            else:
                hint = "allowed: " + ", ".join(sorted(allowed)) if allowed else "no keys allowed"
            self.fail(k, f"unknown key{context} ({hint})")
        for k in required:
            if k not in self.data:
                self.fail(k, f"missing required key{context}")

    # -- scalars --------------------------------------------------------------------
    def number(self, name: str, default: Any = _MISSING, **limits) -> float:
        if name not in self.data:
            if default is _MISSING:
                self.fail(name, "missing required key")
            return default
        return check_number(self.data[name], lambda p: self.fail(name, p), **limits)

    def integer(self, name: str, default: Any = _MISSING, **limits) -> int:
        if name not in self.data:
            if default is _MISSING:
                self.fail(name, "missing required key")
            return default
        return check_number(self.data[name], lambda p: self.fail(name, p), integer=True, **limits)

    def string(self, name: str, default: Any = _MISSING, *, choices: Iterable[str] | None = None) -> str:
        if name not in self.data:
            if default is _MISSING:
                self.fail(name, "missing required key")
            return default
        value = self.data[name]
        if not isinstance(value, str):
            self.fail(name, f"must be a string, got {type_name(value)} {show_value(value)}".rstrip())
        if not value.strip():
            self.fail(name, "must not be empty")
        if any(ord(c) < 32 or ord(c) == 127 for c in value):
            self.fail(name, "must not contain control characters")
        if choices is not None:
            choices = list(choices)
            if value not in choices:
                self.fail(name, f"must be one of {', '.join(map(repr, choices))}, got {show_value(value)}")
        return value

    def boolean(self, name: str, default: Any = _MISSING) -> bool:
        if name not in self.data:
            if default is _MISSING:
                self.fail(name, "missing required key")
            return default
        value = self.data[name]
        if not isinstance(value, bool):
            self.fail(name, f"must be true or false, got {type_name(value)} {show_value(value)}".rstrip())
        return value

    def is_null(self, name: str) -> bool:
        return name in self.data and self.data[name] is None

    # -- arrays ---------------------------------------------------------------------
    def array(self, name: str, default: Any = _MISSING, *, min_len: int = 0,
              max_len: int | None = None) -> list:
        if name not in self.data:
            if default is _MISSING:
                self.fail(name, "missing required key")
            return default
        value = self.data[name]
        if not isinstance(value, list):
            self.fail(name, f"must be an array, got {type_name(value)} {show_value(value)}".rstrip())
        if len(value) < min_len:
            self.fail(name, f"must have at least {min_len} entries, got {_entries(value)}")
        if max_len is not None and len(value) > max_len:
            self.fail(name, f"must have at most {max_len} entries, got {_entries(value)}")
        return value

    def pair(self, name: str, default: Any = _MISSING, *, names: tuple[str, str] = ("x", "y"),
             **limits) -> Point:
        """Two numbers ``[a, b]``; errors name the component (``area: y must be positive``)."""
        if name not in self.data:
            if default is _MISSING:
                self.fail(name, "missing required key")
            return default
        value = self.data[name]
        if not isinstance(value, list) or len(value) != 2:
            got = _entries(value) if isinstance(value, list) else f"{type_name(value)} {show_value(value)}"
            self.fail(name, f"must be an array of two numbers [{names[0]}, {names[1]}], got {got}".rstrip())
        return tuple(
            check_number(v, lambda p, c=c: self.fail(name, f"{c} {p}"), **limits)
            for v, c in zip(value, names)
        )  # type: ignore[return-value]

    def points(self, name: str, *, min_len: int) -> tuple[Point, ...]:
        """An array of ``[x, y]`` points, e.g. a polygon or a path."""
        value = self.array(name, min_len=min_len)
        out = []
        for i, v in enumerate(value, start=1):
            key = f"{name}[{i}]"
            if not isinstance(v, list) or len(v) != 2:
                got = _entries(v) if isinstance(v, list) else f"{type_name(v)} {show_value(v)}"
                self.fail(key, f"must be a point [x, y], got {got}".rstrip())
            out.append(tuple(check_number(c, lambda p, ax=ax, key=key: self.fail(key, f"{ax} {p}"))
                             for c, ax in zip(v, "xy")))
        return tuple(out)  # type: ignore[return-value]

    # -- nesting --------------------------------------------------------------------
    def table(self, name: str, *, optional: bool = False) -> Table | None:
        if name not in self.data:
            if optional:
                return None
            self.fail(name, "missing required table")
        return Table(self.data[name], self.source, self.key(name))

    def tables(self, name: str) -> list[Table]:
        """An array of tables (``[[target]]`` in TOML, a list of objects in JSON)."""
        if name not in self.data:
            return []
        value = self.data[name]
        if isinstance(value, Mapping):
            self.fail(name, f"must be an array of tables (write [[{name}]]), got a single table")
        if not isinstance(value, list):
            self.fail(name, f"must be an array of tables, got {type_name(value)} {show_value(value)}".rstrip())
        return [Table(v, self.source, f"{self.key(name)}[{i}]") for i, v in enumerate(value, start=1)]


def check_format(doc: Mapping[str, Any], source: str | None, expected: str) -> None:
    """``format`` is required and checked before anything else."""
    family = expected.rsplit("/", 1)[0]
    if "format" not in doc:
        raise InputError(source, "format", f"missing required key (expected {expected!r})")
    value = doc["format"]
    if not isinstance(value, str):
        raise InputError(source, "format", f"must be the string {expected!r}, got {type_name(value)}")
    if value == expected:
        return
    if value.rsplit("/", 1)[0] == family:
        raise InputError(source, "format", f"unsupported version {value!r} (this nanoasm reads {expected!r})")
    if value.startswith("nanoasm."):
        raise InputError(source, "format", f"this is a {value!r} file, expected {expected!r}")
    raise InputError(source, "format", f"unknown format {show_value(value)} (expected {expected!r})")
