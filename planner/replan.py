"""Replanning: recompute what remains after the executor's belief changed.

The executor keeps a belief of every object's pose in the layout frame (local scans
corrected by the drift estimate). After each push it asks the :class:`Replanner` for the
rest of the plan. When every object is within ``threshold`` of where the current plan
expected it at this point, the remaining operations stand unchanged (cheap: one pass
over the objects); otherwise the whole remainder is planned again from the belief, and
objects already in their slots stay there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from nanoasm.cad.layout import Layout
from nanoasm.world.environment import EnvObject, Environment

from .assign import axis_error
from .core import PlanStats, Progress, plan_assembly
from .options import PlanOptions
from .plan import Plan


@dataclass(frozen=True)
class Remainder:
    """What is left to do: ``plan.operations`` are the operations still to run."""

    plan: Plan
    replanned: bool
    deviation: float        # largest difference between belief and expectation, nm


def expected(env: Environment, plan: Plan, done: int) -> dict[str, EnvObject]:
    """Poses the plan expects after its first ``done`` operations."""
    objects = {o.id: o for o in env.objects}
    for op in plan.operations[:done]:
        o = objects.get(op.object)
        if o is None:
            continue
        angle = o.angle if op.expect.angle is None or not o.elongated else op.expect.angle
        objects[op.object] = replace(o, at=op.expect.at, angle=angle)
    return objects


def deviation(belief: Environment, expect: dict[str, EnvObject]) -> float:
    """Largest centre (or rod end) distance between belief and expectation; inf if an
    object appeared or vanished."""
    seen = {o.id: o for o in belief.objects}
    if set(seen) != set(expect):
        return math.inf
    worst = 0.0
    for oid, o in seen.items():
        e = expect[oid]
        d = math.dist(o.at, e.at)
        if o.elongated and e.elongated:
            d += math.radians(axis_error(o.angle, e.angle)) * o.length / 2
        worst = max(worst, d)
    return worst


class Replanner:
    """Holds the current plan and replans its remainder when the belief has moved on."""

    def __init__(self, layout: Layout, options: PlanOptions | None = None, *, threshold: float | None = None):
        self.layout = layout
        self.options = options or PlanOptions()
        #: belief-versus-expectation difference that triggers a full replan, nm
        self.threshold = threshold if threshold is not None else min(
            layout.tolerance.position / 2, self.options.margin / 2)
        self.base: Environment | None = None
        self.plan: Plan | None = None
        self.stats: PlanStats | None = None
        self.replans = 0

    def start(self, env: Environment, progress: Progress | None = None) -> Plan:
        self.base = env
        self.plan, self.stats = plan_assembly(self.layout, env, self.options, progress)
        return self.plan

    def remainder(self, belief: Environment, done: int, *, force: bool = False,
                  pivot_offsets: dict[str, float] | None = None) -> Remainder:
        """The operations still to run after ``done`` of the current plan's operations.

        ``done`` counts operations of the plan returned last (after a replan, the new
        plan starts again at 0). ``pivot_offsets``: see :func:`plan_assembly`.
        """
        if self.plan is None or self.base is None:
            raise RuntimeError("call start() before remainder()")
        dev = deviation(belief, expected(self.base, self.plan, done))
        if not force and dev <= self.threshold:
            rest = replace(self.plan, operations=self.plan.operations[done:])
            return Remainder(rest, False, dev)
        self.replans += 1
        self.base = belief
        self.plan, self.stats = plan_assembly(self.layout, belief, self.options, pivot_offsets=pivot_offsets)
        return Remainder(self.plan, True, dev)
