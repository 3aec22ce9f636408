"""Neighbours a push has shoved, looked at again (plan stub; :func:`~.pushing.conclude`
calls :func:`after_push`).

A push's scan after finds its object where it ended. Where that footprint overlaps a
believed neighbour's by more than two scans can err (:data:`OVERLAP`), both cannot lie
there: the neighbour was in the way and the push shoved it. Nothing else would look at it
again before the check scans, and a check scan of an object with neighbours touching it
errs more than one of an object alone (``rods`` seed 5: a particle pushed into the slot
beside a placed rod's end overshot by 27 nm and shoved the rod 22 nm along its axis; the
check scan, its ends hidden by the particles at both, put the rod 16.4 nm from its slot
where it lay 20.9 nm off, tolerance 20, and the report called the slot filled). Such a
neighbour is located again at once, its belief first moved out of the overlap (where the
shove would have put it), and the belief keeps what the scan found; it is named in
``RunContext.shoved`` for the run's loop, which brings a placed one back into its slot
(:func:`~.after_push.shoved_back`).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import shapely
from shapely.ops import nearest_points

from .context import RunContext
from .course import off_course_limit
from .engine import Msg
from .scan_steps import locate

#: A pushed object's measured footprint overlapping a believed neighbour's by more than
#: this (nm) shoved it: two local scans err by a few nm each.
OVERLAP = 6.0


def overlapping(ctx: RunContext, obj_id: str, exclude=()) -> list[tuple[str, np.ndarray]]:
    """Believed neighbours of ``obj_id`` (not in ``exclude``, not lost, not given up, not
    pushed since last seen) whose footprint its own overlaps by more than :data:`OVERLAP`,
    each with the shift (layout frame, nm) that would end the overlap."""
    belief, ledger = ctx.belief, ctx.ledger
    o = belief[obj_id]
    core = o.geometry()
    out = []
    for oid in belief.objects.near(o.at, o.radius + 0.5 * (o.length or 0.0)):
        if oid == obj_id or oid in exclude or oid in belief.lost or oid in ledger.given_up or oid in belief.touched:
            continue
        n = belief[oid]
        g = n.geometry()
        depth = o.radius + n.radius - shapely.distance(core, g)
        if depth <= OVERLAP:
            continue
        p, q = nearest_points(core, g)
        away = np.array([q.x - p.x, q.y - p.y])
        if math.hypot(*away) < 1e-6:                 # cores crossing: away from the pushed centre
            away = np.asarray(n.at, float) - np.asarray(o.at, float)
        norm = math.hypot(*away)
        out.append((oid, away / norm * depth if norm > 1e-9 else np.zeros(2)))
    return out


def after_push(ctx: RunContext, op, body, pending=()):
    """After the push ``op`` whose scan after found its object at ``body`` (layout frame):
    :func:`look_at_shoved`, unless the push left it off course by more than the run
    replans at (:func:`~.course.off_course_limit`). Such a
    push went astray, slipped or was struck by a drift jump, and its object's place
    says nothing of a shove: in ``allpushed`` seed 9 with a 300 nm jump at 750 s, a push
    149 nm off course "shoved" o2, and o2 located again within the jumped estimate was
    another particle, which the jump's recheck then could not set right (7 of 9 slots)."""
    if math.dist(body.at, op.expect.at) <= off_course_limit(ctx.options, body):
        yield from look_at_shoved(ctx, op.object, pending)


def look_at_shoved(ctx: RunContext, obj_id: str, exclude=()):
    """Locate again each neighbour the push of ``obj_id`` shoved (:func:`overlapping`;
    ``exclude``: objects whose belief is not yet where their own push left them) and keep
    what the scans found; each found is added to ``ctx.shoved``. Returns their ids."""
    found_ids = []
    for oid, shift in overlapping(ctx, obj_id, exclude):
        old = ctx.belief[oid]
        guess = np.asarray(old.at, float) + shift
        ctx.belief.objects[oid] = replace(old, at=(float(guess[0]), float(guess[1])))
        found = yield from locate(ctx, oid, widen=False)
        if found is None:                   # where it was believed: the next scan of it searches
            ctx.belief.objects[oid] = old
            yield Msg("event", (f"{oid}: the push of {obj_id} ended over it, and it was not found "
                                f"where that would have shoved it",), {"level": "warn"})
            continue
        scanner, cov, t = found[:3]
        seen = ctx.to_layout(scanner, t)
        ctx.observe(oid, seen.at, t, cov, angle=seen.angle)
        ctx.shoved.add(oid)
        found_ids.append(oid)
        yield Msg("event", (f"{oid}: shoved by the push of {obj_id}, found {math.dist(old.at, seen.at):.1f} nm "
                            f"from where it was believed",), {"level": "warn"})
    return found_ids
