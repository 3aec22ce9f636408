"""Rods by zigzag: pushes near alternate ends, each swinging the rod about a pivot near
the far end (seed §4.3, eq. 4.10), so the rod walks and turns toward its slot.

Primitive: the tip, beside the rod at a fraction ``f`` of its length from one end (never
near l = L/2, the bifurcation), moves straight and perpendicular to the axis by a depth
δ. Under the pivot model the rod turns about the pivot S at s = l + √(l² − lL + L²/2)
from the pushed end (0.74 L for f = 0.1), by φ with tan φ ≈ δ / (s − l); the planner
simulates every push with the model (``nanoasm.world.pivot.rod_step``) to know the pose
it leads to. A pair of equal swings at alternate ends, in the same direction, restores
the angle and moves the rod sideways by ≈ 0.48 φ L; swings at alternate ends in opposite
directions turn it about its centre by 2φ. A controller chooses, push by push:

1. far from the slot along the rod's own axis: turn (about the centre) until the axis is
   perpendicular to the way to go;
2. walk sideways in pairs, the last pair scaled to land on the slot;
3. turn to the slot's angle; then alignment pushes repeat 1-3 on the residual.

Every push's swept area is checked against free space; when the direct approach is
blocked (its straight sweep is not clear, or the search heading straight for the goal
finds no way), an SE(2) path from OMPL (validity over the rod's capsule) provides waypoints.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass, field

import numpy as np
import shapely

from nanoasm.bodies import Body
from nanoasm.world.pivot import RodPose, pivot_position, rod_step

from . import ompl_setup, rod_why
from .assign import axis_error
from .freespace import FreeSpace
from .ompl_setup import Budget
from .options import PlanOptions
from .rod_horizon import plan_swings

Point = tuple[float, float]


@dataclass(frozen=True)
class RodPush:
    """One push: the tip's straight path in contact, and the pose the model predicts."""

    tip_path: tuple[Point, Point]
    pose: Body


def _unit(deg: float) -> tuple[float, float]:
    t = math.radians(deg)
    return math.cos(t), math.sin(t)


def simulate_push(rod: Body, tip0: Point, tip1: Point, tip_radius: float, step: float | None = None,
                  pivot_offset: float = 0.0) -> Body:
    """Pose after the tip moves straight from ``tip0`` to ``tip1`` (pivot model, the pivot
    moved along the axis by ``pivot_offset`` of the length: see ``rod_step``)."""
    pose = RodPose(rod.at[0], rod.at[1], rod.angle, rod.length, rod.diameter)
    dist = math.dist(tip0, tip1)
    n = max(1, math.ceil(dist / (step or max(rod.length / 400.0, 0.5))))
    dx, dy = (tip1[0] - tip0[0]) / n, (tip1[1] - tip0[1]) / n
    x, y = tip0
    for _ in range(n):
        pose = rod_step(pose, (x, y), (dx, dy), tip_radius=tip_radius, pivot_offset=pivot_offset).pose
        x, y = x + dx, y + dy
    # keep the angle continuous (no modulo 180) so "end A" stays the same physical end
    angle = rod.angle + math.remainder(pose.angle - rod.angle, 360.0)
    return Body(rod.id, rod.kind, (pose.x, pose.y), rod.diameter, angle, rod.length)


def push_primitive(rod: Body, end: int, side: int, swing: float, options: PlanOptions) -> tuple[Point, Point]:
    """Tip path of a push near end ``end`` (−1: A, +1: B) toward side ``side`` (+1: +n)
    that turns the rod by about ``swing`` degrees under the pivot model."""
    L, f = rod.length, options.rod_push_point
    l = f * L
    s = float(pivot_position(l, L))                    # from the pushed end (eq. 4.10)
    lever = s - l
    ax, ay = _unit(rod.angle)
    nx, ny = -ay, ax
    u = end * (L / 2 - l)                             # push point along the axis from the centre
    off = rod.radius + options.tip_radius
    px = rod.at[0] + u * ax - side * off * nx
    py = rod.at[1] + u * ay - side * off * ny
    depth = lever * math.tan(math.radians(min(abs(swing), 60.0))) + 0.0
    # the tip starts a little short of contact so the push begins cleanly
    lead = 0.25 * rod.radius
    start = (px - side * lead * nx, py - side * lead * ny)
    end_pt = (px + side * depth * nx, py + side * depth * ny)
    return start, end_pt


def capsule_ends(xs, ys, angles, half: float) -> np.ndarray:
    """End points, shape (n, 2, 2), of core segments of half-length ``half`` (a rod's
    :func:`_half`) at centres ``(xs, ys)`` and axis angles (degrees)."""
    xs, ys, th = (np.asarray(v, float).reshape(-1) for v in (xs, ys, angles))
    c, s = np.cos(np.radians(th)) * half, np.sin(np.radians(th)) * half
    return np.stack([np.column_stack([xs - c, ys - s]), np.column_stack([xs + c, ys + s])], axis=1)


def _cores_of(ends: np.ndarray, half: float) -> np.ndarray:
    """Shapely cores from :func:`capsule_ends` (points where the core has no length)."""
    return shapely.points(ends[:, 0]) if half == 0.0 else shapely.linestrings(ends)


def capsule_cores(xs, ys, angles, length: float, diameter: float) -> np.ndarray:
    """Core segments (shapely, as :meth:`Body.geometry`) of rods of one size at centres
    ``(xs, ys)`` and axis angles (degrees), vectorised."""
    h = max((length - diameter) / 2, 0.0)
    if h == 0.0:
        xs, ys = (np.asarray(v, float).reshape(-1) for v in (xs, ys))
        return shapely.points(np.column_stack([xs, ys]))
    return shapely.linestrings(capsule_ends(xs, ys, angles, h))


def _linear_ends(a: Body, b: Body) -> np.ndarray:
    """Core ends (:func:`capsule_ends`) of the rod at a, b and poses between (2° and a
    radius apart), interpolated along the shorter way round the axis angle."""
    turn = axis_error(a.angle, b.angle)
    n = max(1, math.ceil(turn / 2.0), math.ceil(math.dist(a.at, b.at) / max(a.radius, 1.0)))
    d_ang = math.remainder(b.angle - a.angle, 180.0)
    t = np.linspace(0.0, 1.0, n + 1)
    return capsule_ends(a.at[0] + t * (b.at[0] - a.at[0]), a.at[1] + t * (b.at[1] - a.at[1]),
                        a.angle + t * d_ang, _half(a))


def _half(rod: Body) -> float:
    return max((rod.length - rod.diameter) / 2, 0.0)


def swept_free(space: FreeSpace, a: Body, b: Body, ignore: str | tuple[str, ...], clearance: float | None = None,
               exempt: frozenset[int] = frozenset()) -> bool:
    """The rod's capsule is clear at a, b and poses between (2° apart).

    ``ignore``: the id (or ids) of bodies not to count; ``exempt``: fixed things not to
    count (ones the rod started on, to be pushed off).
    """
    ids = ignore if isinstance(ignore, tuple) else (ignore,)
    return space.all_free(_cores_of(_linear_ends(a, b), _half(a)), a.radius, ids, exempt, clearance)


def _tip_free(space: FreeSpace, tip: Point, tip_radius: float, ignore: str) -> bool:
    """Whether the tip can be put down at ``tip`` without touching anything but the rod."""
    return space.is_free(shapely.Point(tip), tip_radius, (ignore,), clearance=0.0)


@dataclass(frozen=True)
class Macro:
    """A short push sequence and, per push, its tip path and the pose after it, all in
    the rod's own frame (centre at the origin, axis along +x): the pivot model is
    invariant under rigid motions, so one simulation serves every pose."""

    moves: tuple[tuple[int, int, float], ...]
    tips: tuple[tuple[Point, Point], ...]              # in the frame of the macro's start
    poses: tuple[tuple[float, float, float], ...]      # (x, y, angle) after each push, same frame
    #: every push's sweep (:func:`_sweep_ends`), one after the other, same frame
    sweep: np.ndarray = field(compare=False, repr=False)

    @property
    def size(self) -> int:
        return len(self.moves)


def _place(pose: Body, local: tuple[float, float, float]) -> Body:
    c, s = _unit(pose.angle)
    x, y, a = local
    return Body(pose.id, "rod", (pose.at[0] + c * x - s * y, pose.at[1] + s * x + c * y),
                pose.diameter, pose.angle + a, pose.length)


def _place_point(pose: Body, p: Point) -> Point:
    c, s = _unit(pose.angle)
    return pose.at[0] + c * p[0] - s * p[1], pose.at[1] + s * p[0] + c * p[1]


def macro_library(rod: Body, options: PlanOptions, swings: tuple[float, ...], quads: bool) -> list[Macro]:
    """Singles (turn about a pivot near the far end), pairs at alternate ends (walk
    sideways, or turn about the centre) and, if ``quads``, walk-and-return pairs whose
    axial drift moves the rod along its axis."""
    canon = Body(rod.id, "rod", (0.0, 0.0), rod.diameter, 0.0, rod.length)
    seqs = []
    for sw in swings:
        for e in (-1, 1):
            for side in (-1, 1):
                seqs.append(((e, side, sw),))
                seqs.append(((e, side, sw), (-e, side, sw)))        # walk
                seqs.append(((e, side, sw), (-e, -side, sw)))       # turn about the centre
                if quads:
                    seqs.append(((e, side, sw), (-e, side, sw), (e, -side, sw), (-e, -side, sw)))
    out = []
    for seq in seqs:
        pose, tips, poses, sweeps = canon, [], [], []
        for end, side, sw in seq:
            t0, t1 = push_primitive(pose, end, side, sw, options)
            after = simulate_push(pose, t0, t1, options.tip_radius)
            sweeps.append(_sweep_ends(pose, after))
            pose = after
            tips.append((t0, t1))
            poses.append((pose.at[0], pose.at[1], pose.angle))
        out.append(Macro(seq, tuple(tips), tuple(poses), np.concatenate(sweeps)))
    return out


def _sweep_ends(a: Body, b: Body) -> np.ndarray:
    """Core ends (:func:`capsule_ends`) of one push's sweep: the rod turns about a
    (nearly) fixed pivot from a to b, poses at most 2° and one rod radius (at the centre)
    apart."""
    dth = math.radians(b.angle - a.angle)
    if abs(dth) < 1e-9:
        return _linear_ends(a, b)
    # fixed point of the rigid motion a -> b
    c, s = math.cos(dth), math.sin(dth)
    ax, ay = a.at
    bx, by = b.at
    # b = R(a - p) + p  =>  (I - R) p = b - R a
    rx, ry = bx - (c * ax - s * ay), by - (s * ax + c * ay)
    det = (1 - c) ** 2 + s * s
    px = ((1 - c) * rx - s * ry) / det
    py = (s * rx + (1 - c) * ry) / det
    arc = math.hypot(ax - px, ay - py) * abs(dth)          # path of the centre
    n = max(1, math.ceil(abs(math.degrees(dth)) / 2.0), math.ceil(arc / max(a.radius, 1.0)))
    t = dth * np.arange(n + 1) / n
    ct, st = np.cos(t), np.sin(t)
    dx, dy = ax - px, ay - py
    return capsule_ends(px + ct * dx - st * dy, py + st * dx + ct * dy, a.angle + np.degrees(t), _half(a))


def _rotation_sweep(space: FreeSpace, a: Body, b: Body, clearance: float | None,
                    exempt: frozenset[int]) -> bool:
    """Swept check of one push (:func:`_sweep_ends`), all in one query."""
    return space.all_free(_cores_of(_sweep_ends(a, b), _half(a)), a.radius, (a.id,), exempt, clearance)


#: Search expansions one unit of planner budget buys (about a second here: some 2000
#: expansions a second among the bowtie example's objects).
EXPANSIONS_PER_UNIT = 1500
#: The legs along an SE(2) path share this many times the direct search's budget.
LEG_SHARE = 3
#: The lattice search is weighted A* (pushes so far plus ``weight`` times the pushes a
#: sideways walk would still take): the greedy weight finds a way soonest. With
#: ``PlanOptions.rod_search = "refine"``, toward a slot not enclosed by fixed things, the
#: way the direct search found is searched again with the less greedy ``SEARCH_WEIGHT``,
#: within ``REFINE_EXPANSIONS`` and for fewer pushes only, and the shorter kept: fewer
#: pushes on ``rods`` and ``mixed``, but a slot lost on ``rodgap``, so not the default
#: (bench/RESULTS_rods.md, 2026-12-07)
GREEDY_WEIGHT = 2.0
SEARCH_WEIGHT = 1.2
REFINE_EXPANSIONS = EXPANSIONS_PER_UNIT // 2


#: A rod found touching fixed things is pushed off them first by a swing of one of
#: these sizes (degrees, either way, near either end) or a small walk
#: (:meth:`RodController._pushed_off`).
LEAVE_SWINGS = (2.0, 4.0, 8.0, 16.0)
#: How many ways off (nearest the goal first) are planned on from.
LEAVE_TRIES = 3
#: Swings, at most, in a way off; and how many poses still touching are swung again.
LEAVE_DEPTH = 3
LEAVE_FRONTIER = 6
#: Distance, nm, by which a way off may come nearer what it touched between two poses.
LEAVE_SLACK = 0.05


def _deepens(rod: Body, pushes: list[RodPush], touched: list[shapely.Geometry]) -> bool:
    """Whether a push of ``pushes`` (from ``rod``) ever brings the rod's core nearer one of
    ``touched`` on its way (its poses 2° apart, :func:`_sweep_ends`): a way off must leave
    what it touches, not slide along it, where the true rod may lie a few nm otherwise."""
    a = rod
    for p in pushes:
        cores = _cores_of(_sweep_ends(a, p.pose), _half(a))
        for g in touched:
            d = shapely.distance(cores, g)
            if (np.diff(d) < -LEAVE_SLACK).any():
                return True
        a = p.pose
    return False


class RodController:
    """Finds zigzag pushes for one rod: a lattice search over push macros under the pivot
    model (fewest pushes), with swept-area checks; OMPL's SE(2) path guides it when the
    search alone does not get through."""

    def __init__(self, space: FreeSpace, options: PlanOptions, pos_tol: float, ang_tol: float,
                 max_expansions: int = 3000, fixed_names: tuple[str, ...] = ()):
        self.space, self.options = space, options
        #: what each of the space's fixed entries is, for the reasons a search gives
        self.fixed_names = fixed_names
        #: why the last :meth:`pushes` found no way (None after one that did)
        self.failure: str | None = None
        self._nearest: Body | None = None       # the pose a failed search came nearest its goal at
        self._sought: Body | None = None        # and that goal (the slot, or a waypoint on the way)
        self.pos_tol, self.ang_tol = pos_tol, ang_tol
        self.max_expansions = max_expansions
        self.clearance: float | None = None     # None: the space's own (full) clearance
        self.exempt: frozenset[int] = frozenset()
        self._library: dict[tuple, tuple[list[Macro], list[Macro]]] = {}
        #: rods' pivot offsets (fraction of L, along their angle) for the last pushes
        self.offsets: dict[str, float] = {}
        #: search expansions left to the present phase
        self.allowance = Budget(0, math.inf, "rod search")

    # -- macros ---------------------------------------------------------------------
    def _macros(self, rod: Body) -> tuple[list[Macro], list[Macro]]:
        key = (round(rod.length, 6), round(rod.diameter, 6))
        if key not in self._library:
            big = self.options.rod_swing
            far = macro_library(rod, self.options, (big, big / 2, big / 4), quads=False)
            near = macro_library(rod, self.options, (0.5, 1.0, 2.0, 4.0, 8.0, 16.0), quads=True)
            self._library[key] = (far, [m for m in near if max(mv[2] for mv in m.moves) <= big])
        return self._library[key]

    def _realise(self, rod: Body, macro: Macro) -> list[RodPush] | None:
        """World pushes of a macro from ``rod``, or None if any collides: each push's tip
        where it is put down, then its sweep. The sweeps are the macro's own, moved
        rigidly to ``rod`` (the pivot model is invariant under rigid motions), and checked
        against the entries near them all (:meth:`FreeSpace.nearby`: the same answers
        as the space's own checks)."""
        tips = [(_place_point(rod, t0), _place_point(rod, t1)) for t0, t1 in macro.tips]
        c, s = _unit(rod.angle)
        x, y = macro.sweep[..., 0], macro.sweep[..., 1]
        ends = np.stack([rod.at[0] + c * x - s * y, rod.at[1] + s * x + c * y], axis=-1)
        tip_r = self.options.tip_radius
        downs_xy = np.array([w0 for w0, _ in tips])
        # inside the area, from the coordinates themselves (a core's bounds are its ends'),
        # before any geometry is made: the search tries many macros off the area's edge
        flat = ends.reshape(-1, 2)
        e_lo, e_hi, d_lo, d_hi = flat.min(axis=0), flat.max(axis=0), downs_xy.min(axis=0), downs_xy.max(axis=0)
        if not (self.space.inside_box(*e_lo, *e_hi, rod.radius) and self.space.inside_box(*d_lo, *d_hi, tip_r)):
            return None
        cores = _cores_of(ends, _half(rod))
        downs = shapely.points(downs_xy)
        lo, hi = np.minimum(e_lo, d_lo), np.maximum(e_hi, d_hi)
        clear = self.space.clearance if self.clearance is None else self.clearance
        near = self.space.nearby((lo[0], lo[1], hi[0], hi[1]), max(tip_r, rod.radius), max(clear, 0.0))
        # every tip and every sweep clear, or the macro is not taken (none is tried alone)
        if not (near.all_free(downs, tip_r, (rod.id,), clearance=0.0, inside=True)
                and near.all_free(cores, rod.radius, (rod.id,), self.exempt, self.clearance, inside=True)):
            return None
        return [RodPush(tip, _place(rod, local)) for tip, local in zip(tips, macro.poses)]

    # -- goal tests and costs -------------------------------------------------------
    def _done(self, rod: Body, goal: Body, pos_tol: float, ang_tol: float) -> bool:
        return (math.dist(rod.at, goal.at) <= pos_tol
                and abs(math.remainder(goal.angle - rod.angle, 180.0)) <= ang_tol)

    def _cost(self, rod: Body, goal: Body) -> float:
        ang = math.radians(math.remainder(goal.angle - rod.angle, 180.0))
        scale = self.pos_tol / max(math.radians(self.ang_tol), 1e-9)
        return math.hypot(goal.at[0] - rod.at[0], goal.at[1] - rod.at[1], ang * scale)

    # -- search ---------------------------------------------------------------------
    def _search(self, rod: Body, goal: Body, near_pos: float, near_ang: float, refine: bool = False
                ) -> list[RodPush] | None:
        """Pushes to within (near_pos, near_ang) of ``goal``: the greedy search's way, or
        (``refine``) the less greedy search's if that finds a shorter one within its own
        expansions (not counted in the phase's allowance)."""
        found = self._astar(rod, goal, near_pos, near_ang, GREEDY_WEIGHT, self.max_expansions)
        if found is None or not refine or len(found) <= 1:
            return found
        shorter = self._astar(rod, goal, near_pos, near_ang, SEARCH_WEIGHT, REFINE_EXPANSIONS, within=len(found))
        return shorter if shorter is not None else found

    def _astar(self, rod: Body, goal: Body, near_pos: float, near_ang: float, weight: float, most: int,
               within: int | None = None) -> list[RodPush] | None:
        """Weighted A* over far macros (cost: pushes) to within (near_pos, near_ang).
        ``within``: a search for fewer pushes than that (it spends none of the
        allowance and leaves the failure's account alone)."""
        far, _ = self._macros(rod)
        phi = math.radians(self.options.rod_swing)
        lateral = 0.24 * phi * rod.length                   # sideways per push, walking
        cell = max(lateral / 2, 1.0)

        def h(x: float, y: float, a: float) -> float:
            d = math.dist((x, y), goal.at)
            return weight * max(d / lateral, abs(math.remainder(goal.angle - a, 180.0)) / self.options.rod_swing)

        def key(x: float, y: float, a: float) -> tuple:
            return (round(x / cell), round(y / cell), round((a % 180.0) / 6.0) % 30)

        # lazy weighted A*: an edge's collision checks run when its node is popped; a
        # child is a tuple (x, y, angle) until then, made a Body only when popped
        ends = [m.poses[-1] for m in far]
        half = max((rod.length - rod.diameter) / 2, 0.0)
        counter = 0
        heap = [(h(*rod.at, rod.angle), 0, counter, rod, key(*rod.at, rod.angle), None, None)]
        closed: set[tuple] = set()
        expansions = 0
        nearest = (h(*rod.at, rod.angle), rod)        # the pose with the fewest pushes left, by h
        while heap and expansions < most and not self.allowance.exhausted():
            f, g, _, pose, k, parent, macro = heapq.heappop(heap)
            if k in closed or (within is not None and g >= within):
                continue
            trail = None
            if parent is not None:
                pose = Body(rod.id, "rod", (pose[0], pose[1]), rod.diameter, pose[2], rod.length)
                step = self._realise(parent[0], macro)
                if step is None:
                    continue
                trail = (parent[1], step)
            closed.add(k)
            if f - g < nearest[0]:
                nearest = (f - g, pose)
            if self._done(pose, goal, near_pos, near_ang):
                pushes: list[RodPush] = []
                while trail is not None:
                    trail, step = trail
                    pushes[:0] = step
                return pushes
            expansions += 1
            if within is None:
                self.allowance.spend()
            c, s = _unit(pose.angle)
            px, py, pa = pose.at[0], pose.at[1], pose.angle
            for m, (mx, my, ma) in zip(far, ends):
                x, y, a = px + c * mx - s * my, py + s * mx + c * my, pa + ma     # _place(pose, ...)
                ck = key(x, y, a)
                if ck in closed:
                    continue
                ca, sa = _unit(a)           # the core's ends (Body.core), without a shapely geometry
                x0, x1, y0, y1 = x - half * ca, x + half * ca, y - half * sa, y + half * sa
                if not self.space.inside_box(min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1), rod.radius):
                    continue
                counter += 1
                heapq.heappush(heap, (g + m.size + h(x, y, a), g + m.size, counter, (x, y, a), ck, (pose, trail), m))
        if within is None:
            self._nearest, self._sought = nearest[1], goal
        return None

    def _finish(self, rod: Body, goal: Body, budget: int) -> tuple[list[RodPush], Body, bool]:
        """The last pushes into the slot by the receding horizon
        (:mod:`~nanoasm.planner.rod_horizon`); from where it is blocked, or stops getting
        closer, greedy fine macros. Small moves need only avoid contact."""
        saved = self.clearance
        self.clearance = 0.0
        try:
            out, rod = self._finish_horizon(rod, goal, budget)
            if self._done(rod, goal, self.pos_tol, self.ang_tol):
                return out, rod, True
            rest, rod, ok = self._finish_greedy(rod, goal, budget - len(out))
            return out + rest, rod, ok
        finally:
            self.clearance = saved

    def _finish_horizon(self, rod: Body, goal: Body, budget: int) -> tuple[list[RodPush], Body]:
        """Pushes chosen by :func:`~nanoasm.planner.rod_horizon.plan_swings` (its best plan
        that is free of collisions), each made with the full model, while the horizon's
        predicted error at its end keeps falling (its first push may lead away)."""
        o = self.options
        out: list[RodPush] = []
        last = math.inf
        while len(out) < budget and not self._done(rod, goal, self.pos_tol, self.ang_tol):
            plans = plan_swings(rod, goal, push_point=o.rod_push_point, max_swing=o.rod_swing,
                                pos_tol=self.pos_tol, ang_tol=self.ang_tol, offset=self.offsets.get(rod.id, 0.0))
            made = None
            for err, plan in plans:
                if err >= last:
                    break
                made = self._swings(rod, plan)
                if made is not None:
                    last = err
                    break
            if not made:
                break
            out += made
            rod = made[-1].pose
        return out, rod

    def _swings(self, rod: Body, plan: list[tuple[int, float]]) -> list[RodPush] | None:
        """The pushes of ``plan`` made one after the other, or None if one collides."""
        out = []
        for end, swing in plan:
            step = self._swing(rod, end, swing)
            if step is None:
                return None
            out.append(step)
            rod = step.pose
        return out

    def _swing(self, rod: Body, end: int, swing: float) -> RodPush | None:
        """The push near ``end`` that turns ``rod`` by ``swing`` degrees (signed), or None if
        it collides or does not turn the rod that way. A push near end ``e`` toward side
        ``s`` turns the rod by the sign of ``e * s`` (the pivot lies beyond the centre)."""
        if abs(swing) < 1e-3:
            return None
        side = end if swing > 0 else -end
        t0, t1 = push_primitive(rod, end, side, abs(swing), self.options)
        after = simulate_push(rod, t0, t1, self.options.tip_radius, pivot_offset=self.offsets.get(rod.id, 0.0))
        if (after.angle - rod.angle) * swing > 0 and _tip_free(self.space, t0, self.options.tip_radius, rod.id) \
                and _rotation_sweep(self.space, rod, after, self.clearance, self.exempt):
            return RodPush((t0, t1), after)
        return None

    def _finish_greedy(self, rod: Body, goal: Body, budget: int) -> tuple[list[RodPush], Body, bool]:
        _, near = self._macros(rod)
        out: list[RodPush] = []
        while len(out) < budget:
            if self._done(rod, goal, self.pos_tol, self.ang_tol):
                return out, rod, True
            now = self._cost(rod, goal)
            ranked = sorted((self._cost(_place(rod, m.poses[-1]), goal) + 1e-3 * m.size, i)
                            for i, m in enumerate(near))
            step = None
            for cost, i in ranked:
                if cost >= now:
                    break
                step = self._realise(rod, near[i])
                if step is not None:
                    break
            if step is None:
                return out, rod, False
            out += step
            rod = step[-1].pose
        return out, rod, self._done(rod, goal, self.pos_tol, self.ang_tol)

    def _leg(self, rod: Body, goal: Body, near_pos: float, near_ang: float, refine: bool = False
             ) -> list[RodPush] | None:
        if self._done(rod, goal, near_pos, near_ang):
            return []
        return self._search(rod, goal, near_pos, near_ang, refine)

    def pushes(self, rod: Body, goal: Body, max_pushes: int = 80) -> tuple[list[RodPush], Body, bool]:
        """Pushes from ``rod`` to ``goal``; returns them, the final pose, success.

        The budget is counted in search expansions, so a plan does not depend on the
        machine's speed or load: the direct search may expand
        ``EXPANSIONS_PER_UNIT × options.budget`` nodes, the legs along an SE(2) path
        ``LEG_SHARE`` times that together. A wall-clock guard
        (:class:`~nanoasm.planner.ompl_setup.Budget`) only stops a pathological case,
        and says so in the log."""
        self.exempt = self.space.lying_on(rod.geometry(), rod.radius)
        if self.exempt:
            return self._pushed_off(rod, goal, max_pushes)
        cramped = not swept_free(self.space, rod, rod, rod.id, None, self.exempt)
        # a rod that starts closer to its neighbours than the clearance only avoids
        # contact; one whose way with the full clearance is shut (a slot in a gap barely
        # wider than the rod) tries again with the tip's radius
        # a slot with no room to line the rod up in (between electrodes) is entered by a
        # sideways walk, what a zigzag does best, from where there is room (an SE(2) path
        # to there first); the other way round when the direct way fails
        # (the direct search first where the rod's straight way is clear: PlanOptions.rod_direct)
        enclosed = not roomy(self.space, goal, self.options, None, tuple(self.space.bodies))
        # (enclosed: by fixed things, electrodes; an enclosed slot: the walk with the tip's clearance before an SE(2) path, which
        # would have to turn the rod where it has no room to; a slot with room, the direct
        # search and one SE(2) path as ever: a slot no rod reaches is tried again at every
        # replan, and the walk does not help there)
        # the direct search's way searched again for fewer pushes (PlanOptions.rod_search),
        # not toward an enclosed slot, nor the legs along an SE(2) path: refined, they lost
        # the bowtie's rod slot on 3 of 10 seeds
        refine = self.options.rod_search == "refine" and not enclosed
        first = 0.0 if cramped else None
        tries = [(first, enclosed, True)]
        if enclosed:
            tries += [(self.options.tip_radius, True, False)] if not cramped else []
            tries += [(first, False, False)]
        found, why = None, []
        for clearance, approach, direct in tries:
            again = self._pushes(rod, goal, max_pushes, clearance, approach=approach, direct=direct,
                                 refine=refine)
            if again[2]:
                self.failure = None
                return again
            found = found or again
            why.append(self.failure)
        # each try's reason once, in the order tried
        whys = list(dict.fromkeys(w for w in why if w))
        self.failure = "; ".join([rod_why.straight_way(self.space, self.fixed_names, rod, goal), *whys[:1]]
                                 + [f"tried again: {w}" for w in whys[1:]])
        return found

    def _pushed_off(self, rod: Body, goal: Body, max_pushes: int) -> tuple[list[RodPush], Body, bool]:
        """A rod found touching fixed things (an electrode's outline, a keep-out: a push
        that went astray against a pad leaves it there) is first pushed off them: up to
        ``LEAVE_DEPTH`` swings about its pivot (or one small walk), each of which takes it
        away from what it touches all along its sweep (:func:`_deepens`), ending a
        tip's radius clear of everything fixed; the ways off that end nearest the goal
        are tried first. The rest is planned from there with nothing exempt, so no later
        push may slide along what the rod touched (an exemption for the whole plan let a
        walk slide along a pad)."""
        touched = rod_why.listed([rod_why.name(self.fixed_names, i) for i in sorted(self.exempt)])
        ways = self._ways_off(rod, goal)[:LEAVE_TRIES]
        for way in ways:
            rest, pose, ok = self.pushes(way[-1].pose, goal, max(max_pushes - len(way), 0))
            if ok:
                return way + rest, pose, True
        self.failure = (f"it touches {touched}: no swing or small walk takes it off" if not ways else
                        f"it touches {touched}; from the best of {len(ways)} ways off: {self.failure}")
        return [], rod, False

    def _ways_off(self, rod: Body, goal: Body) -> list[list[RodPush]]:
        """Push sequences that take ``rod`` off what it touches (:meth:`_pushed_off`),
        those that end with the space's full clearance first, each kind nearest the goal
        first: a breadth-first search over single swings, the ``LEAVE_FRONTIER`` nearest
        the goal of those still within a tip's radius of what they touched swung again.
        Each swing must leave everything within a tip's radius of its start
        (:func:`_deepens`), not only what it touches."""
        margin = self.options.tip_radius              # room for the next push's sweep to start in
        saved = self.clearance
        self.clearance = 0.0                          # a small move: contact is what it must avoid
        found: list[tuple[tuple[bool, float], list[RodPush]]] = []
        frontier: list[tuple[Body, list[RodPush]]] = [(rod, [])]
        try:
            for depth in range(LEAVE_DEPTH):
                grown = []
                for pose, way in frontier:
                    self.exempt = self.space.lying_on(pose.geometry(), pose.radius)
                    near = set(self.space.fixed_hits(pose.geometry(), pose.radius, margin).tolist())
                    touched = [self.space.fixed_footprint(i) for i in sorted(near)]
                    steps = [[s] for end in (-1, 1) for mag in LEAVE_SWINGS for sign in (-1, 1)
                             if (s := self._swing(pose, end, sign * mag)) is not None]
                    if depth == 0:
                        steps += [s for m in self._macros(pose)[1]
                                  if m.size <= 2 and (s := self._realise(pose, m)) is not None]
                    for step in steps:
                        if _deepens(pose, step, touched):
                            continue
                        end_pose = step[-1].pose
                        cost = self._cost(end_pose, goal) + 1e-3 * (len(way) + len(step))
                        hits = set(self.space.fixed_hits(end_pose.geometry(), end_pose.radius, margin).tolist())
                        if not hits:
                            cramped = bool(self.space.fixed_hits(end_pose.geometry(), end_pose.radius).size)
                            found.append(((cramped, cost), way + step))
                        elif hits <= near:                # still near only what it was near
                            grown.append((cost, way + step))
                grown.sort(key=lambda c: c[0])
                frontier = [(w[-1].pose, w) for _, w in grown[:LEAVE_FRONTIER]]
        finally:
            self.clearance = saved
        found.sort(key=lambda c: c[0])
        return [w for _, w in found]

    def _pushes(self, rod: Body, goal: Body, max_pushes: int, clearance: float | None,
                approach: bool = False, direct: bool = True, refine: bool = False
                ) -> tuple[list[RodPush], Body, bool]:
        near_pos = 0.3 * math.radians(self.options.rod_swing) * rod.length
        near_ang = self.options.rod_swing / 2
        try:
            self.clearance = clearance
            legs = [goal]
            what = f"zigzag of {rod.id!r}"
            self.allowance = Budget.of(self.options, EXPANSIONS_PER_UNIT, what)
            # the direct search where its straight way is clear (or always): blocked, it
            # spends its whole budget before it gives up
            direct = direct and (self.options.rod_direct == "always"
                                 or swept_free(self.space, rod, goal, rod.id, clearance, self.exempt))
            first = self._leg(rod, goal, near_pos, near_ang, refine) if direct else None
            direct_why = (f"the direct search found no way ({self._stuck()})" if direct and first is None
                          else None)
            if first is None:
                self.allowance = Budget.of(self.options, EXPANSIONS_PER_UNIT, what, share=LEG_SHARE)
                # the full clearance along the SE(2) path: a rod's end strays ~15 nm per 2°
                # of its executed angle, and a neighbour it touches hides it from the scans
                self.clearance = clearance
                waypoints = (approach_waypoints(self.space, rod, goal, self.options, clearance) if approach
                             else se2_waypoints(self.space, rod, goal, self.options))
                if not waypoints:
                    self._fail(direct_why, "no approach path into the enclosed slot" if approach else
                               "no SE(2) path (OMPL) within its budget")
                    return [], rod, False
                legs = waypoints[1:]
                # a detour is longer than the straight way the caller's limit was set by
                max_pushes = max(max_pushes, push_limit(rod, waypoints, self.options))
            out: list[RodPush] = []
            pose = rod
            i, fresh_paths = 0, 0
            while i < len(legs):
                step = first if (i == 0 and first is not None) else self._leg(pose, legs[i], near_pos, near_ang)
                if step is None and i + 1 < len(legs) and first is None:
                    # the zigzag ends near, not on, each waypoint: from where it did end,
                    # the next leg may be blocked while the one after is not
                    step = self._leg(pose, legs[i + 1], near_pos, near_ang)
                    i += step is not None
                if step is None:
                    # else a new SE(2) path from there (twice at most)
                    if fresh_paths >= 2 or self.allowance.exhausted() or first is not None:
                        k = next((j for j, w in enumerate(legs) if w is self._sought), i)   # the leg last sought
                        self._fail(direct_why, f"the zigzag along the SE(2) path found no way to its waypoint "
                                   f"{k + 1} of {len(legs)}, {rod_why.where(legs[k], goal)} "
                                   f"({self._stuck('the waypoint')}" + ("; its search budget spent)"
                                                                        if self.allowance.exhausted() else ")"))
                        return out, pose, False
                    fresh_paths += 1
                    waypoints = se2_waypoints(self.space, pose, goal, self.options)
                    if not waypoints:
                        self._fail(direct_why, f"no SE(2) path on from {rod_why.where(pose, goal)}")
                        return out, pose, False
                    legs, i = waypoints[1:], 0
                    continue
                out += step
                pose = out[-1].pose if out else pose
                i += 1
            rest, pose, ok = self._finish(pose, goal, max(max_pushes - len(out), 0))
            n = len(out) + len(rest)
            if not ok:
                self._fail(None, f"the last pushes stopped at {rod_why.where(pose, goal)} (within "
                           f"{self.pos_tol:.0f} nm and {self.ang_tol:.1f}° needed)")
            elif n > max_pushes:
                self._fail(None, f"the way takes {n} pushes, more than the {max_pushes} allowed")
            return out + rest, pose, ok and n <= max_pushes
        finally:
            self.clearance = None

    def _fail(self, *why: str | None) -> None:
        """Say why the present try found no way (:attr:`failure`)."""
        self.failure = "; ".join(w for w in why if w)

    def _stuck(self, what: str = "the slot") -> str:
        """Where the last failed search came nearest its goal (``what``), and what is
        beside it there."""
        if self._nearest is None or self._sought is None:
            return "it expanded nothing"
        return rod_why.stuck(self.space, self.fixed_names, self._nearest, self._sought, self.clearance, what)


def push_limit(rod: Body, poses: list[Body], options: PlanOptions) -> int:
    """Most pushes allowed along ``poses``: a zigzag walks about 0.24 × swing × L a push;
    three times the way, and 40 to finish."""
    per_push = 0.24 * math.radians(options.rod_swing) * rod.length
    way = sum(math.dist(a.at, b.at) for a, b in zip(poses, poses[1:]))
    return 40 + math.ceil(3 * way / per_push)


def _yaw(deg: float) -> float:
    """Degrees to radians in [−π, π), OMPL's SO(2) range (π itself is out of bounds)."""
    return (math.radians(deg) + math.pi) % (2 * math.pi) - math.pi


def se2_waypoints(space: FreeSpace, rod: Body, goal: Body, options: PlanOptions) -> list[Body] | None:
    """Poses from ``rod`` to ``goal`` in SE(2) (OMPL); None when OMPL finds none within
    the budget. The capsule keeps room for the tip on either side of it (a tip diameter
    and the margin) where it can, else the tip radius: a zigzag needs the tip beside
    the rod on both sides, and a path hugging a neighbour leaves it none; a rod that
    starts closer than that to a neighbour only needs to avoid contact."""
    for clearance in (2 * options.tip_radius + options.margin, options.tip_radius, 0.0):
        found = _se2_path(space, rod, goal, options, clearance)
        if found:
            return found
    return None


def roomy(space: FreeSpace, pose: Body, options: PlanOptions, clearance: float | None,
          ignore: tuple[str, ...] = ()) -> bool:
    """Whether a rod at ``pose`` has room to line itself up: to turn by the largest swing
    and to shift along its axis by a fifth of its length, either way (``ignore``: ids of
    bodies not to count, the rod's own among them)."""
    ignore = (pose.id, *ignore)
    th = math.radians(pose.angle)
    shift = 0.2 * pose.length
    moves = [Body(pose.id, "rod", (pose.at[0] + s * shift * math.cos(th), pose.at[1] + s * shift * math.sin(th)),
                  pose.diameter, pose.angle, pose.length) for s in (1.0, -1.0)]
    moves += [Body(pose.id, "rod", pose.at, pose.diameter, pose.angle + s * options.rod_swing, pose.length)
              for s in (1.0, -1.0)]
    return all(swept_free(space, pose, m, ignore, clearance) for m in moves)


def approach_pose(space: FreeSpace, goal: Body, options: PlanOptions, clearance: float | None,
                  rod: Body | None = None, ignore: tuple[str, ...] = ()) -> Body | None:
    """Where a rod at ``goal``'s angle can start a straight sideways walk into it: the
    nearest pose along ``goal``'s normal (either side, in steps of a tenth of its length,
    up to twice its length) that is :func:`roomy`, the way from it to ``goal`` being
    clear. A zigzag moves a rod sideways with ease and along its axis hardly at all, so a
    slot between two electrodes is entered sideways from where there is room to line the
    rod up. The side nearer ``rod`` (when given) first; None when neither side has such
    a pose. Bodies ``ignore`` names do not count (ones that will be moved out of the way)."""
    ignore = (goal.id, *ignore)
    th = math.radians(goal.angle)
    found = []
    for side in (1.0, -1.0):
        nx_, ny_ = -math.sin(th) * side, math.cos(th) * side
        for k in range(1, 21):
            d = 0.1 * k * goal.length
            pre = Body(goal.id, "rod", (goal.at[0] + d * nx_, goal.at[1] + d * ny_), goal.diameter,
                       goal.angle, goal.length)
            if not space.inside(pre.geometry(), pre.radius) or not swept_free(space, goal, pre, ignore, clearance):
                break
            if roomy(space, pre, options, clearance, ignore):
                found.append(pre)
                break
    if rod is not None:
        found.sort(key=lambda p: math.dist(p.at, rod.at))
    return found[0] if found else None


def approach_waypoints(space: FreeSpace, rod: Body, goal: Body, options: PlanOptions,
                       clearance: float | None) -> list[Body] | None:
    """An SE(2) path (:func:`se2_waypoints`) to ``goal``'s :func:`approach_pose`, then the
    straight sideways walk into ``goal`` in legs of a quarter of the rod's length."""
    pre = approach_pose(space, goal, options, clearance, rod)
    if pre is None:
        return None
    pre = Body(rod.id, "rod", pre.at, rod.diameter, pre.angle, rod.length)
    to_pre = se2_waypoints(space, rod, pre, options)
    if not to_pre:
        return None
    n = max(1, math.ceil(math.dist(pre.at, goal.at) / (rod.length / 4)))
    last = to_pre[-1]
    ang = last.angle + math.remainder(goal.angle - last.angle, 180.0)
    walk = [Body(rod.id, "rod", (last.at[0] + (goal.at[0] - last.at[0]) * i / n,
                                 last.at[1] + (goal.at[1] - last.at[1]) * i / n), rod.diameter, ang, rod.length)
            for i in range(1, n + 1)]
    return to_pre + walk


def _se2_path(space: FreeSpace, rod: Body, goal: Body, options: PlanOptions,
              clearance: float) -> list[Body] | None:
    from ompl import base as ob, geometric as og

    ompl_setup.seed(options, 2)
    w, h = space.area
    r = rod.radius
    sp = ob.SE2StateSpace()
    bounds = ob.RealVectorBounds(2)
    bounds.setLow(0, r), bounds.setHigh(0, w - r), bounds.setLow(1, r), bounds.setHigh(1, h - r)
    sp.setBounds(bounds)
    si = ob.SpaceInformation(sp)

    def pose(s) -> Body:
        return Body(rod.id, "rod", (s.getX(), s.getY()), rod.diameter, math.degrees(s.getYaw()), rod.length)

    class Validity(ob.StateValidityChecker):
        def isValid(self, s):
            p = pose(s)
            return swept_free(space, p, p, rod.id, clearance)

    class Sweeps(ob.MotionValidator):
        def checkMotion(self, s1, s2, *rest):
            return swept_free(space, pose(s1), pose(s2), rod.id, clearance)

    validity = Validity(si)
    si.setStateValidityChecker(validity)
    sweeps = Sweeps(si)
    si.setMotionValidator(sweeps)
    si.setup()
    a, b = sp.allocState(), sp.allocState()
    a.setX(rod.at[0]), a.setY(rod.at[1]), a.setYaw(_yaw(rod.angle))
    # a rod's axis is symmetric: aim for the goal angle nearest the current one
    goal_angle = rod.angle + math.remainder(goal.angle - rod.angle, 180.0)
    b.setX(goal.at[0]), b.setY(goal.at[1]), b.setYaw(_yaw(goal_angle))
    path = ompl_setup.solve(si, a, b, options, what=f"SE(2) path of {rod.id!r}")
    if path is None:
        return None
    # shortcut by vertex removal, a fixed amount of work on the seeded RNG: a simplifier
    # given seconds would make the plan depend on the machine's load
    simplifier = og.PathSimplifier(si)
    simplifier.reduceVertices(path)
    simplifier.collapseCloseVertices(path)
    # legs of about a quarter rod length: each is a short search for the zigzag
    length = sum(math.dist((p.getX(), p.getY()), (q.getX(), q.getY()))
                 for p, q in zip(path.getStates(), path.getStates()[1:]))
    path.interpolate(max(2, math.ceil(length / (rod.length / 4)) + 1))
    states = [pose(q) for q in path.getStates()]
    # keep angles continuous along the path
    out = [states[0]]
    for p in states[1:]:
        ang = out[-1].angle + math.remainder(p.angle - out[-1].angle, 360.0)
        out.append(Body(p.id, "rod", p.at, p.diameter, ang, p.length))
    return out
