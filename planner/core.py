"""From a layout and an environment to an ordered list of pushes.

assign (``assign.match``) -> order (``sequence.order``) -> for each move in order, a
path planned against every other object *where it is at that point of the sequence*:
particles by straight segments (``paths``), rods by zigzag pushes (``rods``). Objects in
the way of a move that finds no path are parked first, then the move is tried again.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import shapely

from nanoasm.bodies import Body, geometries
from nanoasm.cad.layout import Layout
from nanoasm.world.environment import Environment, EnvObject

from . import rod_why
from .assign import assignable, compatible, effort, match
from .frames import slots_on_obstacles
from .freespace import FreeSpace
from .options import PlanOptions
from .paths import Mover, centre_path, path_length, turns
from .plan import Assignment, Expect, Operation, Plan, Unfilled
from .rods import RodController, approach_pose, push_limit, roomy
from .sequence import order

Progress = Callable[[int, int], None]


#: How far (nm of radius) an object larger than its slot may reach beyond the slot's
#: footprint at the goal: identification measures diameters to about 1 %, and a slot
#: may touch a keep-out.
SIZE_SLACK = 1.0


@dataclass
class PlanStats:
    """What planning cost and produced, for the CLI summary and the benchmarks."""

    wall_time: float = 0.0
    moves: int = 0
    parked: int = 0
    particle_path_length: float = 0.0
    particle_straight_length: float = 0.0
    particle_turns: list[int] = field(default_factory=list)
    rod_pushes: list[int] = field(default_factory=list)
    ompl_calls: int = 0

    @property
    def path_ratio(self) -> float:
        """Particle path length over straight-line length (1 = straight)."""
        return self.particle_path_length / self.particle_straight_length if self.particle_straight_length else 1.0


class _Session:
    """One planning pass: free space, the growing list of operations, and statistics."""

    def __init__(self, layout: Layout, env: Environment, options: PlanOptions):
        self.layout, self.env, self.options = layout, env, options
        self.targets = {t.id: t for t in layout.targets}
        self.objects: dict[str, EnvObject] = {o.id: o for o in env.objects}
        regions = [k.geometry() for k in layout.regions] + [shapely.Polygon(ob.polygon) for ob in env.obstacles]
        # a rod whose axis lies on a keep-out or an obstacle stays where it is; one that only
        # touches it is pushed off first (RodController._pushed_off), a particle is pushed off
        on_region = set()
        if regions:
            union = shapely.union_all(regions)
            on_region = {o.id for o in env.objects
                         if o.kind == "rod" and shapely.distance(o.geometry(), union) <= 0.0}
        movable = {o.id: o for o in env.objects if assignable(o, options) and o.id not in on_region}
        self.fixed_ids = set(self.objects) - set(movable)
        fixed: list[tuple[shapely.Geometry, float]] = [(g, 0.0) for g in regions]
        held = [self.objects[i] for i in sorted(self.fixed_ids)]
        fixed += [(g, o.radius) for g, o in zip(geometries(held), held)]
        names = rod_why.fixed_names(layout, env.obstacles, sorted(self.fixed_ids))      # in the order of fixed
        area = (min(layout.area[0], env.area[0]), min(layout.area[1], env.area[1]))
        self.space = FreeSpace(area, fixed, movable, options.clearance)
        self.placed: set[str] = set()          # objects in their final slot: never parked
        self.operations: list[Operation] = []
        self.pushed: list[str] = []
        self.stats = PlanStats()
        self.rods = RodController(self.space, options, layout.tolerance.position / 2,
                                  layout.tolerance.angle / 2, fixed_names=names)
        #: why a slot's rod found no way in (:attr:`RodController.failure`), by slot
        self.why: dict[str, str] = {}

    # -- operations -----------------------------------------------------------------
    def _emit(self, obj: Body, target: str | None, tip_path, expect: Body) -> None:
        angle = None if expect.kind != "rod" else expect.angle % 180.0
        self.operations.append(Operation(len(self.operations) + 1, obj.id, target,
                                         tuple((float(x), float(y)) for x, y in tip_path),
                                         Expect((float(expect.at[0]), float(expect.at[1])), angle)))
        if obj.id not in self.pushed:
            self.pushed.append(obj.id)

    def _tip_ok(self, body: Body) -> Callable:
        """Whether the tip can be put down behind a push from a to b: contact-free, except
        with fixed things the object itself lies on (it is being pushed off them)."""
        rt = self.options.tip_radius
        exempt = self.space.lying_on(body.geometry(), body.radius)

        def ok(a, b) -> bool:
            d = math.dist(a, b)
            if d == 0:
                return True
            off = body.radius + rt + self.options.lead
            tip = (a[0] - (b[0] - a[0]) / d * off, a[1] - (b[1] - a[1]) / d * off)
            return self.space.is_free(shapely.Point(tip), rt, (body.id,), exempt, clearance=0.0)
        return ok

    def move_particle(self, obj: EnvObject, goal: tuple[float, float], target: str | None) -> bool:
        # an object identified a hair larger than its slot may still arrive where the slot
        # touches a keep-out; more than SIZE_SLACK larger, it would enter the keep-out
        slot = self.targets.get(target) if target is not None else None
        slack = min(obj.radius - slot.radius, SIZE_SLACK) if slot is not None else 0.0
        mover = Mover(self.space, obj.id, obj.radius, goal_slack=slack)
        path = centre_path(mover, obj.at, goal, self.options, self._tip_ok(obj))
        if path is None:
            return False
        off = obj.radius + self.options.tip_radius
        lead = self.options.lead
        for a, b in zip(path, path[1:]):
            d = math.dist(a, b)
            if d < 1e-6:
                continue
            ux, uy = (b[0] - a[0]) / d, (b[1] - a[1]) / d
            tip = ((a[0] - ux * (off + lead), a[1] - uy * (off + lead)), (b[0] - ux * off, b[1] - uy * off))
            self._emit(obj, target, tip, Body(obj.id, "particle", b, obj.diameter))
        if target is not None:
            self.stats.particle_path_length += path_length(path)
            self.stats.particle_straight_length += math.dist(obj.at, goal)
            self.stats.particle_turns.append(turns(path))
        self._place(obj, Body(obj.id, "particle", goal, obj.diameter))
        return True

    def move_rod(self, obj: EnvObject, goal: Body, target: str | None) -> bool:
        pushes, final, ok = self.rods.pushes(obj, goal, push_limit(obj, [obj, goal], self.options))
        if not ok:
            if target is not None and self.rods.failure:
                self.why[target] = self.rods.failure
            return False
        for p in pushes:
            self._emit(obj, target, p.tip_path, p.pose)
        self.stats.rod_pushes.append(len(pushes))
        self._place(obj, final)
        return True

    def _place(self, obj: EnvObject, pose: Body) -> None:
        new = EnvObject(obj.id, obj.kind, pose.at, obj.diameter, pose.angle, pose.length,
                        obj.confidence, obj.edge)
        self.objects[obj.id] = new
        self.space.move(new)

    # -- moves ----------------------------------------------------------------------
    def fill(self, target_id: str, object_id: str) -> bool:
        t, o = self.targets[target_id], self.objects[object_id]
        for attempt in range(2):
            done = (self.move_rod(o, t, target_id) if o.kind == "rod"
                    else self.move_particle(o, t.at, target_id))
            if done:
                self.placed.add(object_id)
                return True
            if attempt == 0 and not self._clear_way(o, t):
                return False
            o = self.objects[object_id]
        return False

    def _clear_way(self, o: Body, t: Body) -> bool:
        """Park the movable objects in the straight corridor of a move; False if none."""
        corridor = shapely.LineString([o.at, t.at]) if o.at != t.at else shapely.Point(o.at)
        reach = o.length / 2 if o.kind == "rod" else max(o.radius, t.radius)
        blockers = [b for b in self.space.blockers(corridor, reach, (o.id,)) if b not in self.placed]
        blockers += [b for b in self.space.blockers(t.geometry(), t.radius, (o.id,))
                     if b not in self.placed and b not in blockers]
        if o.kind == "rod":    # a rod swings its ends: free the room around where it starts
            blockers += [b for b in self.space.blockers(o.geometry(), o.length / 2, (o.id,))
                         if b not in self.placed and b not in blockers]
            # and, into a slot with no room to line up in, the sideways walk
            # (:func:`~.rods.approach_pose`), were the objects not yet placed out of its way
            loose = tuple(b for b in self.space.bodies if b not in self.placed and b != o.id)
            enclosed = not roomy(self.space, t, self.options, None, tuple(self.space.bodies))
            pre = approach_pose(self.space, t, self.options, None, o, loose) if enclosed else None
            if pre is not None:
                walk = shapely.union(pre.geometry(), t.geometry()).convex_hull
                blockers += [b for b in self.space.blockers(walk, t.radius, (o.id,))
                             if b not in self.placed and b not in blockers]
        parked = [b for b in blockers if self.park(b)]
        return bool(parked)

    def park(self, object_id: str) -> bool:
        """Move an object out of the way, to the nearest place no slot and no corridor needs."""
        o = self.objects[object_id]
        keep_clear = [tg.geometry().buffer(tg.radius + o.radius + self.options.clearance)
                      for tg in self.targets.values()]
        avoid = shapely.union_all(keep_clear) if keep_clear else None
        step = 2 * o.radius + self.options.clearance
        angles = [2 * math.pi * k / 16 for k in range(16)]
        for ring in range(1, 12):
            for a in angles:
                goal = (o.at[0] + ring * step * math.cos(a), o.at[1] + ring * step * math.sin(a))
                pose = (Body(o.id, "particle", goal, o.diameter) if o.kind != "rod" else
                        Body(o.id, "rod", goal, o.diameter, o.angle, o.length))
                if avoid is not None and avoid.intersects(pose.geometry().buffer(o.radius)):
                    continue
                if not self.space.is_free(pose.geometry(), o.radius, (o.id,)):
                    continue
                moved = (self.move_rod(o, pose, None) if o.kind == "rod"
                         else self.move_particle(o, goal, None))
                if moved:
                    self.stats.parked += 1
                    return True
        return False


#: Spare objects tried for a slot whose assigned object finds no way in.
SPARES = 2


def plan_assembly(layout: Layout, env: Environment, options: PlanOptions | None = None,
                  progress: Progress | None = None, pivot_offsets: dict[str, float] | None = None
                  ) -> tuple[Plan, PlanStats]:
    """Plan the assembly of ``layout`` from the objects of ``env``.

    ``pivot_offsets``: rods' pivot offsets (fraction of the length, along each rod's
    ``angle`` in ``env``) as a run has learnt them; the last pushes into a slot use them.
    Deterministic for a given input and ``options.seed``.

    The order of the moves comes from their straight corridors
    (:func:`~nanoasm.planner.sequence.order`), which cannot see a rod's real way in, round
    an electrode and through a gap: a rod slot left with no path after particle slots
    were filled is planned again with the rods first, and the plan that fills more slots
    is kept (``mixed`` seed 5: its rod's way lay between the four particle slots of the
    gap, filled before it; rods first, the plan fills every slot).
    """
    options = options or PlanOptions()
    t0 = time.perf_counter()
    plan, stats, late = _plan(layout, env, options, progress, pivot_offsets, rods_first=False)
    if late:
        again, stats2, _ = _plan(layout, env, options, progress, pivot_offsets, rods_first=True)
        if len(again.assignment) > len(plan.assignment):
            plan, stats = again, stats2
    stats.wall_time = time.perf_counter() - t0
    return plan, stats


def _plan(layout: Layout, env: Environment, options: PlanOptions, progress: Progress | None,
          pivot_offsets: dict[str, float] | None, rods_first: bool) -> tuple[Plan, PlanStats, bool]:
    """One plan (:func:`plan_assembly`), the rods' fills first (after the parkings) if
    ``rods_first``; and whether a rod slot was left with no path after a particle slot
    was filled. The caller sets the plan's wall time."""
    s = _Session(layout, env, options)
    s.rods.offsets = dict(pivot_offsets or {})
    on_obstacle = slots_on_obstacles(layout, env)       # no object can be put there: named, not "no path"
    free = replace(layout, targets=tuple(t for t in layout.targets if t.id not in on_obstacle))
    matching = match(free, [o for o in env.objects if o.id not in s.fixed_ids], options,
                     held=[o for o in env.objects if o.id in s.fixed_ids])
    efforts = {t: effort(s.targets[t], s.objects[o]) for t, o in matching.moves}
    nodes, blocked = order(matching.moves, s.targets, s.objects, s.fixed_ids, options.clearance, efforts)
    if rods_first:
        rods = [n for n in nodes if n[0] == "fill" and s.targets[n[1]].kind == "rod"]
        nodes = [n for n in nodes if n[0] == "park"] + rods + [n for n in nodes if n[0] != "park" and n not in rods]
    object_of = dict(matching.moves)
    for _, o in matching.staying:
        s.placed.add(o)

    done: list[tuple[str, str]] = []
    late = False                    # a rod slot with no path after a particle slot was filled
    unfilled = list(matching.unfilled) + [Unfilled(t, why) for t, why in on_obstacle.items()]
    unfilled += [Unfilled(t, f"slot is held by {s.objects[h].kind} {h!r}, which cannot be pushed")
                 for t, h in sorted(blocked.items())]
    for i, (kind, key) in enumerate(nodes):
        if progress:
            progress(i, len(nodes))
        if kind == "park":
            if key not in s.placed:
                s.park(key)
            continue
        if s.fill(key, object_of[key]):
            done.append((key, object_of[key]))
            continue
        # the assigned particle has no way in (it lies beyond a rod that now closes a gap,
        # say): the nearest spare particles that fit, two at most (not rods: a rod's
        # search costs seconds, and a replan would pay them again)
        claimed = {o for _, o in (*matching.moves, *matching.staying, *done)}
        target = s.targets[key]
        spares = sorted((effort(target, o), o.id) for o in s.objects.values()
                        if target.kind == "particle" and o.id not in claimed and o.id not in s.fixed_ids
                        and o.id not in s.placed and assignable(o, options)
                        and compatible(target, o, layout.tolerance))
        spare = next((o for _, o in spares[:SPARES] if s.fill(key, o)), None)
        if spare is not None:
            done.append((key, spare))
        else:
            why = s.why.get(key) if target.kind == "rod" else None
            unfilled.append(Unfilled(key, f"no path for {object_of[key]!r}" + (f": {why}" if why else "")))
            late = late or (target.kind == "rod" and any(s.targets[t].kind == "particle" for t, _ in done))
    if progress:
        progress(len(nodes), len(nodes))

    order_of = {t.id: i for i, t in enumerate(layout.targets)}
    assignment = sorted([*matching.staying, *done], key=lambda p: order_of[p[0]])
    unfilled.sort(key=lambda u: order_of[u.target])
    plan = Plan(layout.name, tuple(Assignment(t, o) for t, o in assignment), tuple(s.operations),
                tuple(unfilled), layout.registration)
    s.stats.moves = len(done)
    return plan, s.stats, late
