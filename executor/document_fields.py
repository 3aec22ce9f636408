"""Reading stored run documents back, checked: the key readers behind each document's
``from_dict`` (:mod:`nanoasm.executor.documents`), and the error they raise."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from nanoasm.bodies import Body, body_from_table
from nanoasm.errors import InputError
from nanoasm.param import check_number, show_value, type_name
from nanoasm.planner import Operation
from nanoasm.planner.plan import FORMAT as PLAN_FORMAT
from nanoasm.planner.plan import plan_from_dict
from nanoasm.schema import Table
from nanoasm.world.environment import KINDS, EnvObject


class DocumentError(InputError, ValueError):
    """A stored document that is not what its topic holds: names the document and the key."""

    def __init__(self, kind: str, key: str | None, problem: str):
        super().__init__(f"{kind} document", key, problem)


class Fields:
    """The keys of one stored document, read with errors naming the document and the key."""

    def __init__(self, kind: str, data: Any):
        self.kind = kind
        if not isinstance(data, Mapping):
            self.fail(None, f"must be a table, got {type_name(data)}")
        self.data = data

    def fail(self, key: str | None, problem: str):
        raise DocumentError(self.kind, key, problem)

    def get(self, key: str) -> Any:
        if key not in self.data:
            self.fail(key, "missing required key")
        return self.data[key]

    def number(self, key: str, *, optional: bool = False) -> float | None:
        v = self.get(key)
        if v is None and optional:
            return None
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
            self.fail(key, f"must be a number, got {type_name(v)} {show_value(v)}".rstrip())
        return float(v)

    def integer(self, key: str) -> int:
        return int(check_number(self.get(key), lambda p: self.fail(key, p), integer=True))

    def string(self, key: str) -> str:
        v = self.get(key)
        if not isinstance(v, str):
            self.fail(key, f"must be a string, got {type_name(v)} {show_value(v)}".rstrip())
        return v

    def numbers(self, key: str, n: int | None = None, *, optional: bool = False) -> tuple | None:
        """An array of numbers (of ``n`` of them), as a tuple of floats (NaN allowed)."""
        v = self.get(key)
        if v is None and optional:
            return None
        return self.array(key, v, n)

    def array(self, key: str, v: Any, n: int | None = None) -> tuple:
        """``v``, found at ``key``, as a tuple of (``n``) floats."""
        if isinstance(v, np.ndarray):
            v = v.tolist()
        if not isinstance(v, (list, tuple)) or (n is not None and len(v) != n):
            want = "an array of numbers" if n is None else f"an array of {n} numbers"
            self.fail(key, f"must be {want}, got {type_name(v)} {show_value(v)}".rstrip())
        if any(isinstance(x, (bool, str)) for x in v):
            self.fail(key, "must hold numbers only")
        try:
            return tuple(float(x) for x in v)
        except (TypeError, ValueError):
            self.fail(key, "must hold numbers only")

    def mapping(self, key: str, value: type) -> dict:
        """A table of ``value``s (str or float or int) by name."""
        v = self.get(key)
        if not isinstance(v, Mapping):
            self.fail(key, f"must be a table, got {type_name(v)}")
        out = {}
        for k, x in v.items():
            if value is str and not isinstance(x, str):
                self.fail(f"{key}.{k}", f"must be a string, got {type_name(x)}")
            if value is not str:
                x = check_number(x, lambda p, k=k: self.fail(f"{key}.{k}", p), integer=value is int)
            out[str(k)] = value(x)
        return out

    def table(self, key: str) -> Table:
        """A nested table, read with :class:`~nanoasm.schema.Table` (keys named from here)."""
        v = self.get(key)
        if not isinstance(v, Mapping):
            self.fail(key, f"must be a table, got {type_name(v)}")
        return Table(v, f"{self.kind} document", key)

    def parse(self, fn, *args, within: str | None = None):
        """``fn(*args)`` with the errors of the project's readers made DocumentErrors (keys
        named ``within.key`` when ``fn`` reads a table at ``within``)."""
        def key(k: str | None) -> str | None:
            return ".".join(p for p in (within, k) if p) or None

        try:
            return fn(*args)
        except DocumentError:
            raise
        except InputError as err:
            raise DocumentError(self.kind, key(err.key), err.problem) from None
        except KeyError as err:
            raise DocumentError(self.kind, key(str(err.args[0])), "missing required key") from None
        except (ValueError, TypeError, AttributeError, IndexError) as err:
            raise DocumentError(self.kind, key(None), str(err)) from None


def pair(v) -> tuple[float, float]:
    """Two numbers as a tuple of floats."""
    return (float(v[0]), float(v[1]))


def body_from_stored(t: Table) -> Body:
    """A body as :meth:`Body.to_dict` or :meth:`EnvObject.to_dict` wrote it (an EnvObject
    when it has a ``confidence``); InputError naming the key when it is not one."""
    body, extra = body_from_table(t, "", KINDS, extra=("confidence", "edge"))
    if not extra:
        return body
    return EnvObject(body.id, body.kind, body.at, body.diameter, body.angle, body.length,
                     t.number("confidence", 1.0, lo=0.0, hi=1.0), t.boolean("edge", False))


def operation_from_stored(d: Any) -> Operation:
    """An operation as :meth:`Operation.to_dict` wrote it (the plan format's checks)."""
    try:
        return plan_from_dict({"format": PLAN_FORMAT, "operations": [d]}).operations[0]
    except InputError as err:
        key = (err.key or "").replace("operations[1]", "op", 1) or "op"
        raise InputError(err.source, key, err.problem) from None
