"""Report v1 (``nanoasm.report/1``): what a dry-run or run did, with JSON round-trip.

Targets and objects are in the layout's own frame; a layout registered by its marks
adds ``registration``, the transform from that frame to the scan's; a run that executed a
reviewed plan (``--plan``) adds ``plan``, that plan's file."""

from __future__ import annotations

import os
from dataclasses import dataclass, fields

from nanoasm.bodies import Body, body_from_table, check_unique_ids
from nanoasm.cad.frame import Similarity, similarity_from_table
from nanoasm.fileio import dumps_json, read_document, write_atomic
from nanoasm.planner.plan import Assignment, Unfilled, assignments_from, unfilled_from
from nanoasm.schema import Table, check_format

from .slot_verdict import SlotVerdict, verdict_from_table

FORMAT = "nanoasm.report/1"
KINDS = ("particle", "rod")


@dataclass(frozen=True)
class Counts:
    pushes: int = 0
    local_scans: int = 0
    replans: int = 0
    failed_pushes: int = 0


@dataclass(frozen=True)
class InstrumentTime:
    """Seconds the instrument spends, by activity: the parts add up to ``total``
    (``mode_switch``: the approaches into contact before pushes and the switches back to
    tapping before the scan lines after them; absent from reports written before it, read
    as 0; ``travel``: with the lift and park after the run's last step)."""

    full_scan: float = 0.0
    local_scan: float = 0.0
    push: float = 0.0
    travel: float = 0.0
    total: float = 0.0
    mode_switch: float = 0.0


@dataclass(frozen=True)
class WallTime:
    """Seconds of this program's own compute, by stage."""

    identify: float = 0.0
    plan: float = 0.0
    execute: float = 0.0
    total: float = 0.0


def _record_dict(rec) -> dict:
    return {f.name: getattr(rec, f.name) for f in fields(rec)}


#: Record fields that reports written before them lack (read as their default).
_LATER = {"mode_switch"}


def _record(t: Table, name: str, cls, *, integer: bool):
    rt = t.table(name)
    names = [f.name for f in fields(cls)]
    rt.check_keys(required=[n for n in names if n not in _LATER], optional=_LATER & set(names))
    get = rt.integer if integer else rt.number
    return cls(**{n: get(n, nonnegative=True) for n in names if n in rt.data or n not in _LATER})


@dataclass(frozen=True)
class Report:
    scene: str | None
    layout: str | None
    seed: int | None
    targets: tuple[Body, ...]
    initial_objects: tuple[Body, ...]
    final_objects: tuple[Body, ...]
    assignment: tuple[Assignment, ...] = ()
    pushed: tuple[str, ...] = ()
    unfilled: tuple[Unfilled, ...] = ()
    counts: Counts = Counts()
    instrument_time: InstrumentTime = InstrumentTime()
    wall_time: WallTime = WallTime()
    slots: tuple[SlotVerdict, ...] = ()
    registration: Similarity | None = None      # the layout's registration by its marks
    plan: str | None = None                     # the reviewed plan file the run executed (--plan)

    def to_dict(self) -> dict:
        return {
            "format": FORMAT, "scene": self.scene, "layout": self.layout, "seed": self.seed,
            **({} if self.plan is None else {"plan": self.plan}),
            "targets": [t.to_dict() for t in self.targets],
            "initial_objects": [o.to_dict() for o in self.initial_objects],
            "final_objects": [o.to_dict() for o in self.final_objects],
            "assignment": [a.to_dict() for a in self.assignment],
            "pushed": list(self.pushed),
            "unfilled": [u.to_dict() for u in self.unfilled],
            "slots": [v.to_dict() for v in self.slots],
            **({} if self.registration is None else {"registration": self.registration.to_dict()}),
            "counts": _record_dict(self.counts),
            "instrument_time": _record_dict(self.instrument_time),
            "wall_time": _record_dict(self.wall_time),
        }

    def dumps(self) -> str:
        return dumps_json(self.to_dict())

    def save(self, path: str | os.PathLike) -> None:
        write_atomic(path, self.dumps())


def _bodies(t: Table, name: str, prefix: str) -> tuple[Body, ...]:
    tables = t.tables(name)
    bodies = [body_from_table(bt, f"{prefix}{i}", KINDS)[0] for i, bt in enumerate(tables, start=1)]
    check_unique_ids(tables, bodies)
    return tuple(bodies)


def _nullable(t: Table, name: str, getter, **kw):
    return None if t.is_null(name) else getter(name, None, **kw)


def report_from_dict(data: dict, source: str | None = None) -> Report:
    """Validate a parsed ``nanoasm.report/1`` document."""
    check_format(data, source, FORMAT)
    t = Table(data, source)
    keys = ["format", "scene", "layout", "seed", "targets", "initial_objects", "final_objects",
            "assignment", "pushed", "unfilled", "counts", "instrument_time", "wall_time"]
    t.check_keys(required=keys, optional={"slots", "registration", "plan"})
    pushed = t.array("pushed")
    for i, p in enumerate(pushed, start=1):
        if not isinstance(p, str) or not p:
            t.fail(f"pushed[{i}]", "must be an object id (a non-empty string)")
    return Report(
        scene=_nullable(t, "scene", t.string),
        layout=_nullable(t, "layout", t.string),
        seed=_nullable(t, "seed", t.integer, nonnegative=True),
        targets=_bodies(t, "targets", "t"),
        initial_objects=_bodies(t, "initial_objects", "o"),
        final_objects=_bodies(t, "final_objects", "o"),
        assignment=assignments_from(t),
        pushed=tuple(pushed),
        unfilled=unfilled_from(t),
        counts=_record(t, "counts", Counts, integer=True),
        instrument_time=_record(t, "instrument_time", InstrumentTime, integer=False),
        wall_time=_record(t, "wall_time", WallTime, integer=False),
        slots=verdict_from_table(t) if "slots" in data else (),
        registration=None if "registration" not in data else similarity_from_table(t.table("registration")),
        plan=t.string("plan") if "plan" in data else None,
    )


def load_report(path: str | os.PathLike) -> Report:
    return report_from_dict(read_document(path), str(path))
