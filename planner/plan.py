"""Plan v1 (``nanoasm.plan/1``): an ordered list of pushes, with JSON round-trip.

``tip_path`` is the tip's path in contact with the surface, in the layout frame (nm);
moves between pushes are the executor's. ``expect`` is where the pushed object should
end up (``angle`` for rods, ``None`` for particles). A plan of a layout registered by
its marks is in the scan's frame and carries the transform (``registration``).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import NoReturn

from nanoasm.cad.frame import Similarity, similarity_from_table
from nanoasm.fileio import dumps_json, read_document, write_atomic
from nanoasm.param import check_number
from nanoasm.schema import Point, Table, check_format

FORMAT = "nanoasm.plan/1"


def _check_points(points: tuple[Point, ...], what: str) -> None:
    """ValueError naming ``what`` unless every point is two finite numbers."""
    def fail(_problem: str = "") -> NoReturn:
        raise ValueError(f"{what}: every point must be two finite numbers")

    for p in points:
        if len(p) != 2:
            fail()
        for v in p:
            check_number(v, fail)


@dataclass(frozen=True)
class Assignment:
    target: str
    object: str

    def to_dict(self) -> dict:
        return {"target": self.target, "object": self.object}


@dataclass(frozen=True)
class Expect:
    at: Point
    angle: float | None = None

    def __post_init__(self) -> None:
        _check_points((self.at,), "expect.at")
        if self.angle is not None and not math.isfinite(self.angle):
            raise ValueError("expect.angle must be finite or None")

    def to_dict(self) -> dict:
        return {"at": list(self.at), "angle": self.angle}


@dataclass(frozen=True)
class Operation:
    """One push: the tip moves along ``tip_path`` in contact, pushing ``object``.

    ``target`` is the slot the push works towards, or None for a push that only moves
    an object out of the way.
    """

    id: int
    object: str
    target: str | None
    tip_path: tuple[Point, ...]
    expect: Expect
    kind: str = "push"

    def __post_init__(self) -> None:
        if self.kind != "push":
            raise ValueError(f"operation {self.id}: kind must be 'push'")
        if len(self.tip_path) < 2:
            raise ValueError(f"operation {self.id}: tip_path needs at least two points")
        _check_points(self.tip_path, f"operation {self.id}: tip_path")

    def to_dict(self) -> dict:
        return {"id": self.id, "object": self.object, "target": self.target, "kind": self.kind,
                "tip_path": [list(p) for p in self.tip_path], "expect": self.expect.to_dict()}


@dataclass(frozen=True)
class Unfilled:
    target: str
    reason: str

    def to_dict(self) -> dict:
        return {"target": self.target, "reason": self.reason}


@dataclass(frozen=True)
class Plan:
    """A plan; ``registration`` is the transform from the layout's own frame to the
    scan's (whose frame the tip paths are in) when the layout was registered by its marks."""

    layout: str | None
    assignment: tuple[Assignment, ...] = ()
    operations: tuple[Operation, ...] = ()
    unfilled: tuple[Unfilled, ...] = ()
    registration: Similarity | None = None

    def to_dict(self) -> dict:
        d = {"format": FORMAT, "layout": self.layout,
             "assignment": [a.to_dict() for a in self.assignment],
             "operations": [o.to_dict() for o in self.operations],
             "unfilled": [u.to_dict() for u in self.unfilled]}
        if self.registration is not None:
            d["registration"] = self.registration.to_dict()
        return d

    def dumps(self) -> str:
        return dumps_json(self.to_dict())

    def save(self, path: str | os.PathLike) -> None:
        write_atomic(path, self.dumps())


def assignments_from(t: Table) -> tuple[Assignment, ...]:
    """The ``assignment`` array of a plan or report."""
    out = []
    for at in t.tables("assignment"):
        at.check_keys(required={"target", "object"})
        out.append(Assignment(at.string("target"), at.string("object")))
    return tuple(out)


def unfilled_from(t: Table) -> tuple[Unfilled, ...]:
    """The ``unfilled`` array of a plan or report."""
    out = []
    for ut in t.tables("unfilled"):
        ut.check_keys(required={"target", "reason"})
        out.append(Unfilled(ut.string("target"), ut.string("reason")))
    return tuple(out)


def _optional_string(t: Table, name: str) -> str | None:
    return None if t.is_null(name) else t.string(name, None)


def plan_from_dict(data: dict, source: str | None = None) -> Plan:
    """Validate a parsed ``nanoasm.plan/1`` document."""
    check_format(data, source, FORMAT)
    t = Table(data, source)
    t.check_keys(required={"format"}, optional={"layout", "assignment", "operations", "unfilled", "registration"})
    operations = []
    ids: set[int] = set()
    for ot in t.tables("operations"):
        ot.check_keys(required={"id", "object", "kind", "tip_path", "expect"}, optional={"target"})
        op_id = ot.integer("id")
        if op_id in ids:
            ot.fail("id", f"duplicate operation id {op_id}")
        ids.add(op_id)
        ot.string("kind", choices=("push",))
        et = ot.table("expect")
        et.check_keys(required={"at"}, optional={"angle"})
        angle = None if et.is_null("angle") else et.number("angle", None)
        operations.append(Operation(op_id, ot.string("object"), _optional_string(ot, "target"),
                                    ot.points("tip_path", min_len=2), Expect(et.pair("at"), angle)))
    rt = t.table("registration", optional=True)
    return Plan(_optional_string(t, "layout"), assignments_from(t), tuple(operations), unfilled_from(t),
                None if rt is None else similarity_from_table(rt))


def load_plan(path: str | os.PathLike) -> Plan:
    return plan_from_dict(read_document(path), str(path))
