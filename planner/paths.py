"""Collision-free centre paths for pushed objects, with the fewest straight segments.

A straight line is tried first (most pushes in a sparse scene need nothing more); else
OMPL plans in the plane with a shapely-backed validity checker and exact segment checks,
and the result is shortened to the fewest segments, because every turn is a separate
push and turns make pushes fail (seed §4.4.2).

Starts and goals may sit closer to their neighbours than the planning clearance (dense
scenes, touching slots): such an end is joined to free space by one short segment that
only has to avoid contact.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import shapely

from . import ompl_setup
from .freespace import FreeSpace
from .options import PlanOptions

Point = tuple[float, float]
Path = list[Point]

class Mover:
    """Clearance tests for one object of radius ``radius`` moving through ``space``."""

    def __init__(self, space: FreeSpace, body_id: str, radius: float, goal_slack: float = 0.0):
        self.space, self.id, self.radius = space, body_id, radius
        self.exempt: frozenset[int] = frozenset()
        #: how much larger than its slot the object is (radius, nm): arriving at the goal
        #: it need only keep the slot's own footprint out of contact (a slot may touch a
        #: keep-out, and an object a hair larger than the slot is still admitted)
        self.goal_slack = max(float(goal_slack), 0.0)

    def lying_on(self, p: Point) -> None:
        """Let contact-only checks ignore the fixed things the object at ``p`` already
        overlaps (an object found on a keep-out may be pushed off it)."""
        self.exempt = self.space.lying_on(shapely.Point(p), self.radius)

    def free(self, geom: shapely.Geometry, *, clearance: float | None = None) -> bool:
        exempt = self.exempt if clearance == 0 else frozenset()
        return self.space.is_free(geom, self.radius, (self.id,), exempt, clearance)

    def point(self, p: Point, **kw) -> bool:
        return self.free(shapely.Point(p), **kw)

    def segment(self, a: Point, b: Point, **kw) -> bool:
        if a == b:
            return self.point(a, **kw)
        return self.free(shapely.LineString([a, b]), **kw)

    def relaxed(self, a: Point, b: Point, relax_a: float = 0.0, relax_b: float = 0.0) -> bool:
        """Segment check where the parts within ``relax_a`` of a and ``relax_b`` of b need
        only avoid contact (crowded starts and goals), the rest full clearance."""
        length = math.dist(a, b)
        if relax_a + relax_b >= length:
            if relax_b and self.goal_slack and not relax_a:
                return self._arriving(a, b)
            return self.segment(a, b, clearance=0.0 if relax_a or relax_b else None)
        ux, uy = (b[0] - a[0]) / length, (b[1] - a[1]) / length
        a2 = (a[0] + ux * relax_a, a[1] + uy * relax_a)
        b2 = (b[0] - ux * relax_b, b[1] - uy * relax_b)
        return ((not relax_a or self.segment(a, a2, clearance=0.0)) and self.segment(a2, b2)
                and (not relax_b or self._arriving(b2, b)))

    def _arriving(self, a: Point, b: Point) -> bool:
        """Contact-only check of the last part of a move into the goal: with the radius
        less :attr:`goal_slack` against fixed things (a slot may touch a keep-out), with
        the whole radius against the other objects (the slack is no licence to touch one)."""
        geom = shapely.Point(a) if a == b else shapely.LineString([a, b])
        if not self.space.is_free(geom, self.radius - self.goal_slack, (self.id,), self.exempt, 0.0):
            return False
        return not self.goal_slack or not self.space.blockers(geom, self.radius, (self.id,), clearance=0.0)

    def slack(self, p: Point) -> float:
        return self.space.slack(shapely.Point(p), self.radius, (self.id,))


def _directions(n: int, toward: Point | None, origin: Point) -> list[float]:
    """Angles (radians) sorted by how well they point ``toward`` (all n when None)."""
    angles = [2 * math.pi * k / n for k in range(n)]
    if toward is None:
        return angles
    aim = math.atan2(toward[1] - origin[1], toward[0] - origin[0])
    return sorted(angles, key=lambda a: abs(math.remainder(a - aim, 2 * math.pi)))


def connector(mover: Mover, end: Point, toward: Point | None, reach: float,
              ok: Callable[[Point, Point], bool], *, arriving: bool) -> Point | None:
    """A point of full clearance within ``reach`` of a crowded ``end``, one push away.

    For a start (``arriving`` False) the object leaves ``end``; for a goal it arrives at
    ``end``. Directions toward ``toward`` are preferred; distances grow from one step.
    """
    step = mover.radius + mover.space.clearance
    for dist in np.linspace(step, reach, 3):
        for a in _directions(24, toward, end):
            p = (end[0] + dist * math.cos(a), end[1] + dist * math.sin(a))
            if mover.point(p) and (ok(p, end) if arriving else ok(end, p)):
                return p
    return None


def fewest_segments(path: Path, segment_free: Callable[[Point, Point], bool]) -> Path:
    """Greedy farthest-visible shortcutting: keeps the fewest vertices it can."""
    if len(path) <= 2:
        return list(path)
    out = [path[0]]
    i = 0
    while i < len(path) - 1:
        j = len(path) - 1
        while j > i + 1 and not segment_free(path[i], path[j]):
            j -= 1
        out.append(path[j])
        i = j
    return out


def ompl_path(mover: Mover, start: Point, goal: Point, options: PlanOptions) -> Path | None:
    """Plan with OMPL from ``start`` to ``goal`` (both of full clearance); None if none found."""
    from ompl import base as ob

    ompl_setup.seed(options, 1)
    r = mover.radius
    w, h = mover.space.area
    space = ob.RealVectorStateSpace(2)
    bounds = ob.RealVectorBounds(2)
    bounds.setLow(0, r), bounds.setHigh(0, w - r), bounds.setLow(1, r), bounds.setHigh(1, h - r)
    space.setBounds(bounds)
    si = ob.SpaceInformation(space)

    class Validity(ob.StateValidityChecker):
        def isValid(self, s):
            return mover.point((s[0], s[1]))

        def clearance(self, s):
            return mover.slack((s[0], s[1]))

    class Segments(ob.MotionValidator):
        def checkMotion(self, s1, s2, *rest):
            return mover.segment((s1[0], s1[1]), (s2[0], s2[1]))

    class ClearanceCost(ob.StateCostIntegralObjective):
        """Cost that grows as the path nears obstacles (OMPL's clearance objective)."""

        def stateCost(self, s):
            return ob.Cost(1.0 / (max(mover.slack((s[0], s[1])), 0.0) + r))

    def length_and_clearance(si):
        # an optimising planner weighs clearance against length and uses its whole budget
        objective = ob.MultiOptimizationObjective(si)
        objective.addObjective(ob.PathLengthOptimizationObjective(si), 1.0)
        objective.addObjective(ClearanceCost(si, True), r * r)
        objective.setCostThreshold(ob.Cost(0.0))
        return objective

    validity = Validity(si)
    si.setStateValidityChecker(validity)
    segments = Segments(si)
    si.setMotionValidator(segments)
    si.setup()
    a, b = space.allocState(), space.allocState()
    a[0], a[1] = start
    b[0], b[1] = goal
    path = ompl_setup.solve(si, a, b, options, what=f"path of {mover.id!r}", objective=length_and_clearance)
    if path is None:
        return None
    states = path.getStates()
    return [(float(q[0]), float(q[1])) for q in states]


def centre_path(mover: Mover, start: Point, goal: Point, options: PlanOptions,
                tip_ok: Callable[[Point, Point], bool]) -> Path | None:
    """Fewest-segment collision-free path of the object's centre, or None.

    ``tip_ok(a, b)`` tells whether the tip can be put down behind a push from a to b.
    """
    if math.dist(start, goal) < 1e-9:
        return [start]
    reach = 3 * (mover.radius + mover.space.clearance)
    mover.lying_on(start)
    relax_start = 0.0 if mover.point(start) else reach
    relax_goal = 0.0 if mover.point(goal) else reach

    def ok(p: Point, q: Point) -> bool:
        return tip_ok(p, q) and mover.relaxed(p, q, relax_start if p == start else 0.0,
                                              relax_goal if q == goal else 0.0)

    if ok(start, goal):
        return [start, goal]
    a = start if not relax_start else connector(mover, start, goal, reach, ok, arriving=False)
    b = goal if not relax_goal else connector(mover, goal, start, reach, ok, arriving=True)
    if a is None or b is None:
        return None
    middle = [a, b] if ok(a, b) else ompl_path(mover, a, b, options)
    if middle is None:
        return None
    path = ([start] if a != start else []) + middle + ([goal] if b != goal else [])
    return fewest_segments(path, ok)


def path_length(path: Path) -> float:
    return float(sum(math.dist(a, b) for a, b in zip(path, path[1:])))


def turns(path: Path) -> int:
    return max(len(path) - 2, 0)
