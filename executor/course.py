"""Following the plan: the pose each operation expects to start from, the preload raised for
objects the tip slipped over, whether a rod's course stays clear of its neighbours, and
the extra pushes that bring an object that missed its slot back in."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field, replace

import numpy as np
import shapely

from nanoasm.bodies import Body
from nanoasm.cad.layout import Layout
from nanoasm.planner import Operation, PlanOptions
from nanoasm.planner.assign import in_slot
from nanoasm.world.environment import Environment

from .belief import Belief
from .json_parts import Kept, PartsDict, kept

#: An object the tip slipped over is pushed with this many times the preload, again...
SLIP_PRELOAD_STEP = 1.6
#: ...up to this many times the nominal preload.
SLIP_PRELOAD_MAX = 4.0


@dataclass
class Course:
    """Where the plan expects each operation's object to start (``starts``: op id ->
    ``(at, angle)``, layout frame) and the preload factor per object (``preload``)."""

    starts: dict[int, tuple] = field(default_factory=dict)
    preload: dict[str, float] = field(default_factory=dict)
    #: ``(starts, their JSON types as a kept part)`` (:mod:`.json_parts`): the same
    #: hundreds of starts in every checkpoint until :meth:`follow` makes new ones
    _kept: tuple[dict, Kept] | None = field(default=None, init=False, repr=False, compare=False)

    def follow(self, env: Environment, ops: list[Operation], *, extend: bool = False) -> None:
        """Expect ``ops`` from the poses of ``env`` (adding to the present ones if ``extend``)."""
        new = starts(env, ops)
        self.starts = {**self.starts, **new} if extend else new     # a new dict: the kept part goes with it

    def slipped(self, obj_id: str) -> None:
        """The tip went over ``obj_id``: push it harder next time."""
        self.preload[obj_id] = min(self.preload.get(obj_id, 1.0) * SLIP_PRELOAD_STEP, SLIP_PRELOAD_MAX)

    def state_dict(self) -> dict:
        if self._kept is None or self._kept[0] is not self.starts:     # the starts are never changed in place
            self._kept = (self.starts, kept({str(k): [list(at), ang] for k, (at, ang) in self.starts.items()}))
        return PartsDict(plan_start=self._kept[1], preload_factor=dict(self.preload))

    @classmethod
    def from_state(cls, state: dict) -> Course:
        return cls({int(k): (tuple(v[0]), v[1]) for k, v in state["plan_start"].items()},
                   {k: float(v) for k, v in state["preload_factor"].items()})


def starts(env: Environment, ops: list[Operation]) -> dict[int, tuple]:
    """Pose ``(at, angle)`` the plan expects each operation's object to start from."""
    pose = {o.id: (o.at, o.angle) for o in env.objects}
    out = {}
    for op in ops:
        out[op.id] = pose.get(op.object, (op.expect.at, op.expect.angle))
        pose[op.object] = (op.expect.at, op.expect.angle)
    return out


def course_clear(o: Body, upcoming_starts: dict[int, tuple], rest: list[Operation], others: list[Body],
                 tip_radius: float) -> bool:
    """Whether rod ``o``'s next planned poses, carried along by its present deviation from
    the plan (re-aiming keeps that deviation: shift and turn), stay clear of ``others`` by
    the tip radius. A rod's pushes scatter by a few nm and degrees; along a course
    planned 30 nm from a neighbour, the deviation adds up until the rod touches it (and
    the scans then cannot tell the two apart)."""
    upcoming = list(itertools.takewhile(lambda p: p.object == o.id, rest))
    if not upcoming or upcoming[0].id not in upcoming_starts:
        return True
    (ex, ey), ea = upcoming_starts[upcoming[0].id]
    if ea is None or o.angle is None:
        return True
    shift = np.asarray(o.at, float) - (ex, ey)
    turn = math.remainder(o.angle - ea, 180.0)
    if not others:
        return True
    cores = np.array([b.geometry() for b in others], dtype=object)
    reach = np.array([b.radius for b in others]) + o.radius + tip_radius
    tree = shapely.STRtree(cores)
    for p in upcoming:
        at = np.asarray(p.expect.at, float) + shift
        body = Body(o.id, "rod", (float(at[0]), float(at[1])), o.diameter,
                    (p.expect.angle or 0.0) + turn, o.length)
        g = body.geometry()
        idx = tree.query(g, predicate="dwithin", distance=float(reach.max()))
        if idx.size and (shapely.distance(g, cores[idx]) < reach[idx]).any():
            return False
    return True


def off_course_limit(options, o) -> float:
    """How far (nm) a push may leave object ``o`` from where the plan expects it before
    the rest is planned again (``options``: the run's ExecOptions): ``replan_after``; a
    rod's pushes scatter more (pivot, path), and re-aiming absorbs up to L/4."""
    return max(options.replan_after, o.length / 4) if o.kind == "rod" and o.length else options.replan_after


def tight(layout: Layout):
    """A tolerance tighter than the layout's: correct what would be borderline."""
    t = layout.tolerance
    return replace(t, position=t.position * 0.6, angle=t.angle * 0.6)


def correction(layout: Layout, belief: Belief, target_id: str, obj_id: str, used: dict[str, int],
               max_corrections: int, options: PlanOptions, first_id: int) -> list[Operation] | None:
    """Pushes that bring object ``obj_id``, which missed slot ``target_id``, back in (a
    single-object plan, its operations numbered from ``first_id``); None when none is
    needed or allowed. ``used`` counts the corrections per object (at most
    ``max_corrections``)."""
    from nanoasm.planner import plan_assembly

    target = layout.target(target_id)
    o = belief[obj_id]
    if in_slot(target, o, tight(layout)) or used.get(o.id, 0) >= max_corrections:
        return None
    used[o.id] = used.get(o.id, 0) + 1
    solo = replace(layout, targets=(target,), tolerance=tight(layout))
    # the other objects are only in the way here: no confidence, never assigned
    others = tuple(b.changed(confidence=0.0) for oid, b in belief.objects.items()
                   if oid != o.id and oid not in belief.lost)
    env = Environment(belief.area, (o, *others), belief.obstacles)
    plan, _ = plan_assembly(solo, env, options)
    mine = [p for p in plan.operations if p.object == o.id]
    return [replace(p, id=first_id + k) for k, p in enumerate(mine)]
