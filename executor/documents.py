"""Run documents: what a run tells its subscribers, typed, on named topics.

The engine and the procedure send a document on a topic (:data:`TOPICS`) to every
subscriber (the run log, the dry-run harness, progress displays). Each document is a
frozen dataclass whose ``to_dict()`` is what the run log keeps (JSON types) and whose
``from_dict()`` reads a stored one back, checked: a missing key or a value of the wrong
type is a :class:`DocumentError` naming the document and the key. The identified
environment and the plans are sent as :class:`~nanoasm.world.environment.Environment`
and :class:`~nanoasm.planner.Plan` (their own formats, ``nanoasm.env/1`` and
``nanoasm.plan/1``). Positions in nm, times in instrument seconds.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from nanoasm.bodies import Body
from nanoasm.param import show_value, type_name
from nanoasm.planner import Operation
from nanoasm.planner.plan import Assignment, Unfilled, assignments_from, plan_from_dict, unfilled_from
from nanoasm.schema import Table
from nanoasm.world.environment import environment_from_dict

from .belief import Belief
from .document_fields import DocumentError, Fields, body_from_stored, operation_from_stored, pair
from .ledger import RunLedger
from .slot_verdict import verdict_from_table

# -- topics -------------------------------------------------------------------------------
EVENT = "event"                  #: a log line (:class:`EventDoc`)
DAC = "dac"                      #: a streamed DAC chunk, downsampled (:class:`DacDoc`)
FULL_SCAN = "full_scan"          #: the first full scan (:class:`FullScanDoc`)
ENVIRONMENT = "environment"      #: what the full scan identified (an Environment)
PLAN = "plan"                    #: the first plan and every replan (a Plan)
PUSH = "push"                    #: one push done (:class:`PushDoc`)
DRIFT = "drift"                  #: the drift estimate after an update (:class:`DriftDoc`)
SCAN_LINE = "scan_line"          #: one local-scan line (:class:`ScanLineDoc`)
CHECKPOINT = "checkpoint"        #: the procedure's state after a push (:class:`CheckpointDoc`)
RESULT = "result"                #: what the run did (:class:`ResultDoc`)
STOP = "stop"                    #: how the run ended, sent once at the end (:class:`StopDoc`)
TOPICS = (EVENT, DAC, FULL_SCAN, ENVIRONMENT, PLAN, PUSH, DRIFT, SCAN_LINE, CHECKPOINT, RESULT, STOP)

#: Topic -> the run log's JSON channel that keeps its documents as ``to_dict()`` gives them.
CHANNELS = {ENVIRONMENT: "/environment", PLAN: "/plan", PUSH: "/push", DRIFT: "/drift",
            SCAN_LINE: "/local_scan", DAC: "/dac", CHECKPOINT: "/checkpoint", RESULT: "/result",
            STOP: "/stop"}

#: Push verdicts that mean the push failed (anything else, "pushing", went as planned).
FAILED_VERDICTS = ("slipped", "stuck", "no_contact")

#: The checkpoint format (the procedure's state; :mod:`nanoasm.executor.checkpoints`).
CHECKPOINT_FORMAT = "nanoasm.checkpoint/1"


class Document(Protocol):
    """Anything sent on a topic: it gives the dict the run log keeps."""

    def to_dict(self) -> dict: ...


def as_dict(doc: Document | dict) -> dict:
    """A document as the dict the run log keeps (a dict as it is).

    TRANSITION: some producers still emit plain dicts; this goes once all of them emit
    documents (subscribers then call ``doc.to_dict()``)."""
    return doc if isinstance(doc, dict) else doc.to_dict()


# -- the documents ----------------------------------------------------------------------------
@dataclass(frozen=True)
class EventDoc:
    """A log line at instrument time ``t``: ``level`` info, warn or error."""

    t: float
    level: str
    text: str

    def to_dict(self) -> dict:
        return {"t": self.t, "level": self.level, "text": self.text}

    @classmethod
    def from_dict(cls, d: Any) -> EventDoc:
        f = Fields(EVENT, d)
        return cls(f.number("t"), f.string("level"), f.string("text"))


@dataclass(frozen=True)
class StopDoc:
    """How the run ended: the engine's final ``state`` (done, failed, aborted) and why."""

    state: str
    reason: str

    def to_dict(self) -> dict:
        return {"state": self.state, "reason": self.reason}

    @classmethod
    def from_dict(cls, d: Any) -> StopDoc:
        f = Fields(STOP, d)
        return cls(f.string("state"), f.string("reason"))


@dataclass(frozen=True)
class PushDoc:
    """One push done: the operation, its verdict, the end time, the drift offset then
    (scanner position of the layout origin), the object's pose before (layout frame),
    the peak lateral force (nN) and the belief about the object after; for a rod, its
    pivot offset estimate (``{offset, std, pushes}``, fractions of its length: see
    :mod:`~nanoasm.executor.pivots`), None otherwise."""

    op: Operation
    verdict: str
    t: float
    offset: tuple[float, float]
    before: tuple[float, float]
    peak_force: float | None
    belief: Body
    pivot: dict | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "offset", pair(self.offset))
        object.__setattr__(self, "before", pair(self.before))
        if self.peak_force is not None:
            object.__setattr__(self, "peak_force", float(self.peak_force))

    @property
    def failed(self) -> bool:
        """Whether the push failed (:data:`FAILED_VERDICTS`)."""
        return self.verdict in FAILED_VERDICTS

    def to_dict(self) -> dict:
        d = {"op": self.op.to_dict(), "verdict": self.verdict, "t": self.t, "offset": list(self.offset),
             "before": list(self.before), "peak_force": self.peak_force, "belief": self.belief.to_dict()}
        if self.pivot is not None:
            d["pivot"] = dict(self.pivot)
        return d

    @classmethod
    def from_dict(cls, d: Any) -> PushDoc:
        f = Fields(PUSH, d)
        op = f.parse(operation_from_stored, f.get("op"))
        belief = f.parse(body_from_stored, f.table("belief"))
        pivot = f.mapping("pivot", float) if f.data.get("pivot") is not None else None
        return cls(op, f.string("verdict"), f.number("t"), f.numbers("offset", 2), f.numbers("before", 2),
                   f.number("peak_force", optional=True), belief, pivot)


@dataclass(frozen=True)
class DriftDoc:
    """The drift estimate at ``t``: offset since the start (nm), its covariance (nm²) and
    the drift velocity (nm/s), None for an estimator that has none."""

    t: float
    offset: tuple[float, float]
    cov: tuple[tuple[float, float], tuple[float, float]] | None
    velocity: tuple[float, float] | None

    def __post_init__(self) -> None:
        object.__setattr__(self, "offset", pair(self.offset))
        if self.cov is not None:
            object.__setattr__(self, "cov", (pair(self.cov[0]), pair(self.cov[1])))
        if self.velocity is not None:
            object.__setattr__(self, "velocity", pair(self.velocity))

    def to_dict(self) -> dict:
        return {"t": self.t, "offset": list(self.offset),
                "cov": None if self.cov is None else [list(r) for r in self.cov],
                "velocity": None if self.velocity is None else list(self.velocity)}

    @classmethod
    def from_dict(cls, d: Any) -> DriftDoc:
        f = Fields(DRIFT, d)
        cov = f.get("cov")
        if cov is not None:
            if not isinstance(cov, list) or len(cov) != 2:
                f.fail("cov", f"must be a 2 x 2 array of numbers or null, got {type_name(cov)}")
            cov = tuple(f.array(f"cov[{i}]", row, 2) for i, row in enumerate(cov))
        return cls(f.number("t"), f.numbers("offset", 2), cov, f.numbers("velocity", 2, optional=True))


@dataclass(frozen=True)
class ScanLineDoc:
    """One local-scan line: end points ``a``, ``b`` (scanner frame), the heights along it
    (nm) and the scanner position of the layout origin then (layout = scanner - offset)."""

    t: float
    a: tuple[float, float]
    b: tuple[float, float]
    heights: tuple[float, ...]
    offset: tuple[float, float]

    def __post_init__(self) -> None:
        object.__setattr__(self, "a", pair(self.a))
        object.__setattr__(self, "b", pair(self.b))
        object.__setattr__(self, "heights", tuple(np.asarray(self.heights, float).tolist()))
        object.__setattr__(self, "offset", pair(self.offset))

    def to_dict(self) -> dict:
        return {"t": self.t, "a": list(self.a), "b": list(self.b), "heights": list(self.heights),
                "offset": list(self.offset)}

    @classmethod
    def from_dict(cls, d: Any) -> ScanLineDoc:
        f = Fields(SCAN_LINE, d)
        return cls(f.number("t"), f.numbers("a", 2), f.numbers("b", 2), f.numbers("heights"),
                   f.numbers("offset", 2))


@dataclass(frozen=True)
class DacDoc:
    """A streamed DAC chunk, every ``every``-th of its ``n`` samples: time (s), scanner
    XYZ (nm), the sample kind and the photodiode signals S_n, S_l."""

    t: tuple[float, ...]
    x: tuple[float, ...]
    y: tuple[float, ...]
    z: tuple[float, ...]
    kind: tuple[int, ...]
    s_n: tuple[float, ...]
    s_l: tuple[float, ...]
    n: int
    every: int

    def __post_init__(self) -> None:
        for name in ("t", "x", "y", "z", "s_n", "s_l"):
            object.__setattr__(self, name, tuple(np.asarray(getattr(self, name), float).tolist()))
        object.__setattr__(self, "kind", tuple(np.asarray(self.kind, int).tolist()))
        if not len(self.t) == len(self.x) == len(self.y) == len(self.z) == len(self.kind) == len(self.s_n) \
                == len(self.s_l):
            raise DocumentError(DAC, None, "t, x, y, z, kind, s_n and s_l must be as long as each other")

    def to_dict(self) -> dict:
        return {"t": list(self.t), "x": list(self.x), "y": list(self.y), "z": list(self.z),
                "kind": list(self.kind), "s_n": list(self.s_n), "s_l": list(self.s_l), "n": self.n,
                "every": self.every}

    @classmethod
    def from_dict(cls, d: Any) -> DacDoc:
        f = Fields(DAC, d)
        kind = f.numbers("kind")
        if any(k != int(k) for k in kind):
            f.fail("kind", "must hold integers only")
        return cls(*(f.numbers(k) for k in ("t", "x", "y", "z")), tuple(int(k) for k in kind),
                   f.numbers("s_n"), f.numbers("s_l"), f.integer("n"), f.integer("every"))


@dataclass(frozen=True, eq=False)
class FullScanDoc:
    """The first full scan: heights (nm, rows bottom to top), pixel size (nm) and the
    image's lower-left corner in the layout frame, at the end time ``t``."""

    t: float
    height: np.ndarray
    pixel_size: float
    origin: tuple[float, float]

    def __post_init__(self) -> None:
        object.__setattr__(self, "origin", pair(self.origin))

    def to_dict(self) -> dict:
        return {"t": self.t, "height": self.height, "pixel_size": self.pixel_size, "origin": self.origin}

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, FullScanDoc):
            return NotImplemented
        return (self.t, self.pixel_size, tuple(self.origin)) == (other.t, other.pixel_size, tuple(other.origin)) \
            and np.array_equal(self.height, other.height)

    __hash__ = None  # type: ignore[assignment]

    @classmethod
    def from_dict(cls, d: Any) -> FullScanDoc:
        f = Fields(FULL_SCAN, d)
        try:
            height = np.asarray(f.get("height"), float)
        except (TypeError, ValueError):
            f.fail("height", "must be a 2-D array of numbers")
        if height.ndim != 2:
            f.fail("height", f"must be a 2-D array of numbers, got {height.ndim} dimension(s)")
        return cls(f.number("t"), height, f.number("pixel_size"), f.numbers("origin", 2))


@dataclass(frozen=True)
class CheckpointDoc:
    """The procedure's state after a push (``nanoasm.checkpoint/1``; its keys are the
    executor's, :mod:`nanoasm.executor.checkpoints`) and the latest drift estimate
    ``(t, x, y)`` (scanner offset, nm), if any."""

    state: dict
    drift: tuple[float, float, float] | None

    @property
    def t(self) -> float:
        """Instrument time of the checkpoint."""
        return float(self.state["t"])

    def to_dict(self) -> dict:
        return {**self.state, "drift": None if self.drift is None else list(self.drift)}

    def belief(self) -> Belief:
        """The executor's belief then (:meth:`Belief.from_state`); DocumentError when the
        state holds none."""
        f = Fields(CHECKPOINT, self.state)
        return f.parse(Belief.from_state, f.get("belief"), within="belief")

    def ledger(self) -> RunLedger:
        """What the run had done by then (:meth:`RunLedger.from_state`); DocumentError
        when the state does not tell."""
        return Fields(CHECKPOINT, self.state).parse(RunLedger.from_state, self.state)

    @classmethod
    def from_dict(cls, d: Any) -> CheckpointDoc:
        f = Fields(CHECKPOINT, d)
        if f.get("format") != CHECKPOINT_FORMAT:
            f.fail("format", f"must be {CHECKPOINT_FORMAT!r}, got {show_value(d['format'])}")
        f.number("t")
        drift = f.numbers("drift", 3, optional=True)
        return cls({k: v for k, v in d.items() if k != "drift"}, drift)


@dataclass(frozen=True)
class ResultDoc:
    """What the run did: the slots assigned (less objects lost) and not, the objects
    pushed, counts, instrument time by activity (s), compute time by stage (s), failures
    ``(object, cause)``, the run's start (the layout frame's time), the layout origin
    in the scanner frame then, the instrument seconds the drift measurements took by
    purpose (reference, relocalise, bootstrap) and the verdict of the final check scans
    on every slot (both optional: logs before them lack them)."""

    assignment: tuple[Assignment, ...]
    unfilled: tuple[Unfilled, ...]
    pushed: tuple[str, ...]
    counts: dict[str, int]
    times: dict[str, float]
    wall: dict[str, float]
    failures: tuple[tuple[str, str], ...]
    epoch: float
    origin: tuple[float, float]
    purposes: dict[str, float] | None = None
    slots: tuple = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "assignment", tuple(self.assignment))
        object.__setattr__(self, "unfilled", tuple(self.unfilled))
        object.__setattr__(self, "pushed", tuple(self.pushed))
        object.__setattr__(self, "failures", tuple((o, c) for o, c in self.failures))
        object.__setattr__(self, "origin", pair(self.origin))

    def to_dict(self) -> dict:
        return {"assignment": [a.to_dict() for a in self.assignment],
                "unfilled": [u.to_dict() for u in self.unfilled],
                "pushed": list(self.pushed), "counts": dict(self.counts), "times": dict(self.times),
                "wall": dict(self.wall), "failures": [{"object": o, "cause": c} for o, c in self.failures],
                "epoch": self.epoch, "origin": list(self.origin),
                **({} if self.purposes is None else {"purposes": dict(self.purposes)}),
                **({"slots": [v.to_dict() for v in self.slots]} if self.slots else {})}

    @classmethod
    def from_dict(cls, d: Any) -> ResultDoc:
        f = Fields(RESULT, d)
        t = Table(d, f"{RESULT} document")
        for key in ("assignment", "unfilled", "failures"):
            f.get(key)
        assignment = f.parse(assignments_from, t)
        unfilled = f.parse(unfilled_from, t)
        pushed = f.get("pushed")
        if not isinstance(pushed, list) or not all(isinstance(p, str) for p in pushed):
            f.fail("pushed", "must be an array of object ids (strings)")
        failures = []
        for ft in f.parse(t.tables, "failures"):
            failures.append(f.parse(lambda ft=ft: (ft.string("object"), ft.string("cause"))))
        return cls(assignment, unfilled, tuple(pushed), f.mapping("counts", int), f.mapping("times", float),
                   f.mapping("wall", float), tuple(failures), f.number("epoch"), f.numbers("origin", 2),
                   f.mapping("purposes", float) if d.get("purposes") is not None else None,
                   f.parse(verdict_from_table, t) if d.get("slots") else ())


#: Topic -> the document type its stored dicts are read back as.
TYPES = {EVENT: EventDoc, STOP: StopDoc, PUSH: PushDoc, DRIFT: DriftDoc, SCAN_LINE: ScanLineDoc,
         DAC: DacDoc, FULL_SCAN: FullScanDoc, CHECKPOINT: CheckpointDoc, RESULT: ResultDoc}


def document_from_dict(topic: str, d: Any):
    """A stored document of ``topic`` read back: a document of :data:`TYPES`, an
    Environment or a Plan; DocumentError when it is not what the topic holds."""
    if topic == ENVIRONMENT:
        return Fields(ENVIRONMENT, d).parse(environment_from_dict, d, f"{ENVIRONMENT} document")
    if topic == PLAN:
        return Fields(PLAN, d).parse(plan_from_dict, d, f"{PLAN} document")
    if topic not in TYPES:
        raise DocumentError(topic, None, f"unknown topic; one of {', '.join(TOPICS)}")
    return TYPES[topic].from_dict(d)
