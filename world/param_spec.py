"""Parameter groups as TOML tables: the reader, the writer and the docs.

A parameter group is a frozen dataclass whose fields are made with
:func:`nanoasm.param.param` and checked by :func:`nanoasm.param.validate` (see
:mod:`nanoasm.param`). :func:`from_table` reads one from a
:class:`~nanoasm.schema.Table` (unknown keys are rejected with a suggestion),
:func:`to_table` writes only the values that differ from the defaults, and
:func:`markdown_rows` documents it.
"""

from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

from nanoasm.param import ParamError, check_field
from nanoasm.schema import Table

T = TypeVar("T")


def from_table(cls: type[T], t: Table) -> T:
    """Read a parameter group from one table; errors name the file and the key path."""
    fields = dataclasses.fields(cls)
    t.check_keys(required=[f.name for f in fields if f.metadata["required"]],
                 optional=[f.name for f in fields])
    kwargs = {}
    for f in fields:
        if f.name in t:
            kwargs[f.name] = check_field(f, t.data[f.name], lambda p, n=f.name: t.fail(n, p))
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
