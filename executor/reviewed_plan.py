"""Running a reviewed plan: a plan file made before the run (``nanoasm plan``'s,
``nanoasm.plan/1``) executed after the drift bootstrap instead of a plan of the run's own,
as long as the scene it was made for is still the scene the full scan shows.

Before anything moves, :func:`load_reviewed` checks the plan against the layout (the
same slots, each assigned object taken to its slot, registered by the marks or not
alike). After the full scan, :meth:`ReviewedPlan.adopt` finds every object of the plan
among the identified ones, in the drift-corrected frame (the layout frame; a plan made
with a registered layout is moved from its scan's frame into this run's by the two
registrations). The plan file holds no object list, so where it had each object is read
from its pushes: a particle's first push puts the tip down its radius, the tip's and
``lead`` behind it, on the line to the push's end (the planner's geometry,
``planner.core._Session.move_particle``); a rod's first push is the pivot-model primitive
of its pose (:func:`nanoasm.planner.rods.push_primitive`); an assigned object that is not
pushed lies in its slot. An object missing, turned into another kind or moved more than
the limit (the layout's ``tolerance.position`` or ``PIXELS_SLACK`` pixels of the full
scan, whichever is larger), or an object the plan does not know of on a planned path, is
one InputError naming the plan file and what changed; nothing has been pushed then.
Otherwise the plan, its objects renamed to the run's ids, is the run's first plan:
replans after it are as in any run.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, replace

import numpy as np
import shapely
from scipy.optimize import linear_sum_assignment

from nanoasm.bodies import Body
from nanoasm.cad.layout import Layout
from nanoasm.errors import InputError
from nanoasm.planner import Plan, PlanOptions
from nanoasm.planner.assign import axis_error
from nanoasm.planner.plan import Expect, Operation, load_plan
from nanoasm.planner.rods import push_primitive, simulate_push
from nanoasm.world.environment import Environment, EnvObject

#: The limit on how far an object may have moved since the plan: the layout's
#: ``tolerance.position`` or this many pixels of the full scan, whichever is larger.
PIXELS_SLACK = 3
#: Farther than this (nm) from where the plan had it, an object of the plan is gone.
REACH = 1000.0
Point = tuple[float, float]


@dataclass(frozen=True)
class Planned:
    """An object of the plan where the plan had it: a particle's centre, a rod's first
    push (``first``), or the slot of an object the plan leaves there (``stays``)."""

    id: str
    kind: str
    at: Point
    first: Operation | None = None
    stays: bool = False


def _unit(a: Point, b: Point) -> tuple[float, float]:
    d = math.dist(a, b)
    return ((b[0] - a[0]) / d, (b[1] - a[1]) / d) if d > 0 else (0.0, 0.0)


def planned_objects(plan: Plan, layout: Layout, options: PlanOptions) -> dict[str, Planned]:
    """Every object the plan pushes or assigns, where the plan had it (see the module's
    docstring); ``layout`` in the plan's frame."""
    out: dict[str, Planned] = {}
    for op in plan.operations:
        if op.object in out:
            continue
        if op.expect.angle is not None:
            out[op.object] = Planned(op.object, "rod", op.tip_path[0], op)
            continue
        t0, t1 = op.tip_path[0], op.tip_path[-1]
        back = math.dist(t1, op.expect.at) + options.lead        # object radius + tip radius + lead
        ux, uy = _unit(t0, t1)
        out[op.object] = Planned(op.object, "particle", (t0[0] + ux * back, t0[1] + uy * back), op)
    for a in plan.assignment:
        if a.object not in out:
            t = layout.target(a.target)
            out[a.object] = Planned(a.object, t.kind, t.at, stays=True)
    return out


def offset(p: Planned, o: EnvObject, options: PlanOptions) -> float:
    """How far (nm) ``o`` lies from where the plan had ``p``. A rod: the larger of how far
    its first push's tip start lies from where the primitive puts it on ``o``, and how far
    the pose that push leaves ``o`` in (the pivot model) is from the plan's, its turn
    counted at the rod's ends."""
    if p.kind != "rod" or p.first is None:
        return math.dist(p.at, o.at)
    op = p.first
    # the nearest of the primitive's four starts (either end, either side; the swing moves
    # only where it ends)
    contact = min(math.dist(p.at, push_primitive(o, end, side, 0.0, options)[0])
                  for end in (-1, 1) for side in (-1, 1))
    after = simulate_push(o, op.tip_path[0], op.tip_path[-1], options.tip_radius)
    turn = math.radians(axis_error(after.angle, op.expect.angle)) * o.length / 2
    return max(contact, math.dist(after.at, op.expect.at) + turn)


def _mapping(plan: Plan, run: Layout):
    """Point and angle maps from the plan's frame into this run's (through the layout's
    own frame when both registered it by its marks; else the frames are one)."""
    before, now = plan.registration, run.registration
    if before is None or now is None:
        return (lambda p: (float(p[0]), float(p[1]))), 0.0
    back = before.inverse()
    return (lambda p: now.point(back.point(p))), now.rotation - before.rotation


@dataclass(frozen=True)
class ReviewedPlan:
    """A plan file (``source``) checked against the layout, to be adopted after the full scan."""

    plan: Plan
    source: str

    def adopt(self, layout: Layout, env: Environment, resolution: float, options: PlanOptions) -> tuple[Plan, str]:
        """The plan in this run's frame and ids (``layout`` and ``env``: the run's, the
        objects drift-corrected; ``resolution``: the full scan's pixel size, nm) and the
        run's line on it, or an InputError naming what changed since it was made."""
        move, turn = _mapping(self.plan, layout)
        plan = self.plan
        ops = tuple(replace(op, tip_path=tuple(move(p) for p in op.tip_path),
                            expect=Expect(move(op.expect.at), None if op.expect.angle is None
                                          else (op.expect.angle + turn) % 180.0)) for op in plan.operations)
        plan = replace(plan, operations=ops, registration=layout.registration)
        limit = max(layout.tolerance.position, PIXELS_SLACK * resolution)
        planned = planned_objects(plan, layout, options)
        ids, offsets = self._match(planned, env, options, layout.tolerance.position)
        problems = self._changes(planned, env, ids, offsets, limit)
        problems += _in_the_way(plan, planned, env, ids, options, limit)
        if problems:
            more = f", and {len(problems) - 1} more change(s)" if len(problems) > 1 else ""
            raise InputError(self.source, None, f"{problems[0]}{more}; plan again")
        plan = replace(plan, assignment=tuple(replace(a, object=ids[a.object]) for a in plan.assignment),
                       operations=tuple(replace(op, object=ids[op.object]) for op in plan.operations))
        worst = max(offsets.values(), default=0.0)
        return plan, (f"plan: the reviewed plan {self.source}: {len(plan.assignment)} slot(s) assigned, "
                      f"{len(plan.operations)} push(es); its objects found within {worst:.0f} nm of where it "
                      f"had them (limit {limit:.0f} nm)")

    def _match(self, planned: dict[str, Planned], env: Environment, options: PlanOptions, slack: float):
        """The plan's objects paired one to one with the identified ones of their kind
        (least total offset, none beyond ``REACH``): plan id -> run id, and each offset
        (an object left in its slot: beyond ``slack`` of it)."""
        ps, os_ = list(planned.values()), [o for o in env.objects if o.kind in ("particle", "rod")]
        if not ps or not os_:
            return {}, {}
        cost = np.full((len(ps), len(os_)), np.inf)
        for i, p in enumerate(ps):
            for j, o in enumerate(os_):
                if o.kind == p.kind and math.dist(p.at, o.at) <= REACH + (o.length or 0.0) / 2:
                    cost[i, j] = max(offset(p, o, options) - (slack if p.stays else 0.0), 0.0)
        finite = np.where(np.isfinite(cost), cost, 1e12)
        rows, cols = linear_sum_assignment(finite)
        pairs = [(ps[i], os_[j], cost[i, j]) for i, j in zip(rows, cols) if cost[i, j] <= REACH]
        return {p.id: o.id for p, o, _ in pairs}, {p.id: float(c) for p, _, c in pairs}

    def _changes(self, planned, env, ids, offsets, limit) -> list[str]:
        """What changed, the gravest first: objects gone (or of another kind now), objects
        moved together (the sample drifted) or alone, the largest first."""
        out = []
        for p in planned.values():
            if p.id in ids:
                continue
            near = min(env.objects, key=lambda o: math.dist(o.at, p.at), default=None)
            if near is not None and near.kind != p.kind and math.dist(near.at, p.at) <= limit:
                out.append(f"object {p.id} was a {p.kind} and is now a {near.kind}")
            else:
                out.append(f"object {p.id} (a {p.kind} near ({p.at[0]:.0f}, {p.at[1]:.0f})) is gone: no {p.kind} "
                           f"within {REACH:.0f} nm")
        moved = sorted(((c, pid) for pid, c in offsets.items() if c > limit), reverse=True)
        objects = {o.id: o for o in env.objects}
        shifts = np.array([np.subtract(objects[ids[p.id]].at, p.at) for p in planned.values()
                           if p.id in ids and p.kind == "particle" and not p.stays])
        if len(moved) >= 3 and len(shifts) >= 3:
            common = np.median(shifts, axis=0)
            if (np.hypot(*common) > limit
                    and np.mean(np.hypot(*(shifts - common).T) <= limit) >= 2 / 3):
                return out + [f"the objects moved together by ({common[0]:.0f}, {common[1]:.0f}) nm since the "
                              f"plan (limit {limit:.0f} nm): the sample drifted, or this full scan is not where "
                              f"the plan's scan was (--region)"]
        return out + [f"object {pid} moved {c:.0f} nm since the plan (limit {limit:.0f} nm)"
                      if planned[pid].kind != "rod" or planned[pid].stays else
                      f"rod {pid} moved or turned since the plan: its first push would leave it {c:.0f} nm off "
                      f"the plan's pose (limit {limit:.0f} nm)" for c, pid in moved]


def _in_the_way(plan: Plan, planned: dict[str, Planned], env: Environment, ids: dict[str, str],
                options: PlanOptions, limit: float) -> list[str]:
    """Objects the plan does not know of (matched to none of its objects) that its pushes
    would run into: a pushed particle's path, or a rod's pose after a push, within the
    object's footprint plus the planner's clearance, less ``limit``."""
    objects = {o.id: o for o in env.objects}
    others = [o for o in env.objects if o.id not in set(ids.values())]
    at: dict[str, Point] = {pid: p.at for pid, p in planned.items()}
    out: list[str] = []
    for op in plan.operations:
        if not others:
            break
        if planned[op.object].kind == "rod":
            rod = objects.get(ids.get(op.object, ""))
            if rod is None:
                continue
            swept = Body(rod.id, "rod", op.expect.at, rod.diameter, op.expect.angle, rod.length).geometry()
            reach = rod.radius
        else:
            swept = shapely.LineString([at[op.object], op.expect.at])
            reach = math.dist(op.tip_path[-1], op.expect.at) - options.tip_radius
            at[op.object] = op.expect.at
        hit = next((o for o in others if shapely.distance(swept, o.geometry())
                    < reach + o.radius + options.clearance - limit), None)
        if hit is not None:
            others.remove(hit)
            out.append(f"a {hit.kind} at ({hit.at[0]:.0f}, {hit.at[1]:.0f}), not in the plan, lies in the way of "
                       f"push {op.id} ({op.object})")
    return out


def first_plan(replanner, reviewed: ReviewedPlan | None, layout: Layout, env: Environment,
               pixel_size: float) -> tuple[Plan, str]:
    """A run's first plan and its line: ``replanner``'s own from ``env`` (the belief,
    drift-corrected), or the ``reviewed`` plan in the run's frame and ids, which the
    replanner then holds as its current plan (an InputError when the scene changed since
    it was made; ``pixel_size``: the full scan's)."""
    if reviewed is None:
        plan = replanner.start(env)
        return plan, f"plan: {len(plan.assignment)} slot(s) assigned, {len(plan.operations)} push(es)"
    plan, line = reviewed.adopt(layout, env, pixel_size, replanner.options)
    replanner.base, replanner.plan = env, plan
    return plan, line


def load_reviewed(path: str | os.PathLike, layout: Layout, layout_source: str, align: str) -> ReviewedPlan:
    """The plan file at ``path`` (read by :func:`~nanoasm.planner.plan.load_plan`), refused
    in one line naming it unless it was made for ``layout`` (file ``layout_source``): the
    same slots, each assigned object taken to its slot, registered by its marks as this
    run will (``align``) or not."""
    source = str(path)
    plan = load_plan(path)

    def refuse(problem: str):
        raise InputError(source, None, f"{problem}; plan again")

    if plan.layout is not None and layout.name is not None and plan.layout != layout.name:
        refuse(f"made for layout {plan.layout!r}, not {layout.name!r} ({layout_source})")
    mine = {t.id for t in layout.targets}
    theirs = {a.target for a in plan.assignment} | {u.target for u in plan.unfilled}
    if mine != theirs:
        extra, missing = sorted(theirs - mine), sorted(mine - theirs)
        refuse(f"its slots are not those of {layout_source}"
               + (f" ({', '.join(extra[:5])} not in it)" if extra else "")
               + (f" ({', '.join(missing[:5])} missing)" if missing else ""))
    registers = bool(layout.marks) and align != "none"
    if registers != (plan.registration is not None):
        refuse("made with the layout registered by its marks, and this run takes the layout's frame for the "
               "scan's (--no-align)" if not registers else
               "made without registering the layout by its marks (--no-align), and this run registers it")
    frame = layout if plan.registration is None else layout.mapped(plan.registration, layout.area)
    for a in plan.assignment:
        last = [op for op in plan.operations if op.object == a.object and op.target == a.target]
        t = frame.target(a.target)
        if last and math.dist(last[-1].expect.at, t.at) > layout.tolerance.position * (
                1.0 if plan.registration is None else plan.registration.scale) + 1.0:
            x, y = last[-1].expect.at
            refuse(f"slot {a.target} is at ({t.at[0]:.0f}, {t.at[1]:.0f}) in {layout_source}, and the plan "
                   f"takes {a.object} to ({x:.0f}, {y:.0f})")
    return ReviewedPlan(plan, source)
