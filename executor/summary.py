"""What a run did, for the report and the run log's ``/result`` (the truth is the dry-run
harness's business)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from nanoasm.planner import Plan
from nanoasm.planner.plan import Assignment, Unfilled
from nanoasm.world.environment import Environment

from .belief import Belief
from .report import Counts


@dataclass
class RunSummary:
    """What a run did: the identified environment, the first plan, the final belief, the
    slots assigned and not, and the ledger's figures."""

    env: Environment                      # identified at the start
    plan: Plan                            # first plan
    belief: Belief
    assignment: tuple[Assignment, ...] = ()
    unfilled: tuple[Unfilled, ...] = ()
    pushed: list[str] = field(default_factory=list)
    counts: Counts = Counts()
    times: dict[str, float] = field(default_factory=dict)
    wall: dict[str, float] = field(default_factory=dict)
    drift: list[tuple[float, float, float]] = field(default_factory=list)   # (t, x, y) scanner offsets
    failures: list[tuple[str, str]] = field(default_factory=list)          # (object, cause)
    epoch: float = 0.0            # start of the run: the layout frame's time
    origin: tuple[float, float] = (0.0, 0.0)   # layout origin in the scanner frame at the epoch
    purposes: dict[str, float] = field(default_factory=dict)   # drift measurements' instrument s
    slots: tuple = ()             # the run's verdict on every slot (executor.verdict.SlotVerdict)
    registration: Any = None      # the layout's registration by its marks (cad.frame.Similarity), if any

    def to_doc(self) -> dict:
        """What the run did, for the run log."""
        return {"assignment": [a.to_dict() for a in self.assignment],
                "unfilled": [u.to_dict() for u in self.unfilled],
                "pushed": list(self.pushed), "counts": dict(vars(self.counts)), "times": dict(self.times),
                "wall": dict(self.wall), "failures": [{"object": o, "cause": c} for o, c in self.failures],
                "epoch": self.epoch, "origin": list(self.origin), "purposes": dict(self.purposes),
                "slots": [v.to_dict() for v in self.slots]}


def summary(asm) -> RunSummary:
    """The summary of an :class:`~nanoasm.executor.assembly.Assembly` as it stands: the
    latest plan's assignment, less the objects lost on the way."""
    ctx = asm.ctx
    plan = asm.replanner.plan or asm.first_plan
    lost = ctx.belief.lost
    assignment, unfilled = [], list(plan.unfilled)
    for a in plan.assignment:
        if a.object in lost:
            unfilled.append(Unfilled(a.target, f"object {a.object!r} was lost during the run"))
        else:
            assignment.append(a)
    # a slot the check found filled by an object the plan had not assigned to it
    # (verdict._named): that object is what fills it
    held, used = {a.target for a in assignment}, {a.object for a in assignment}
    for v in getattr(asm, "slots", ()):
        if v.state == "filled" and v.object is not None and v.target not in held and v.object not in used:
            assignment.append(Assignment(v.target, v.object))
            unfilled = [u for u in unfilled if u.target != v.target]
    led, drift = ctx.ledger, ctx.drift
    return RunSummary(asm.env, asm.first_plan, ctx.belief, tuple(assignment), tuple(unfilled), led.pushed,
                      led.count(), dict(led.times), dict(led.wall), led.drift, led.failures, drift.epoch,
                      (float(drift.origin[0]), float(drift.origin[1])), dict(led.purposes),
                      tuple(getattr(asm, "slots", ())), asm.layout.registration)
