"""After a relocalisation: which object is which among those the jumped drift may have
confused (plan stubs; :func:`~nanoasm.executor.relocalise.relocalise` calls
:func:`recheck`).

The drift may have jumped at any time after the estimate was last confirmed and before
the first reference it failed. Objects seen in between were put into the layout frame
with the old estimate, before or after the jump: each is looked for where the
relocalisation's correction puts it, else where it was believed.

The pushes made in between went where the tip truly was: if the drift had jumped, that
is their path less the correction. An object lying on that corrected path may have been
shoved by them, and what a push's after-scan found at its expected end (the correction's
place of the pushed object) may be that object, not the one pushed. So each such
object is looked for where it was believed first; one no longer there was displaced,
the place a push it lay on left its pushed object at is its own, and that pushed
object is looked for where it was believed before the correction (where it was pushed
to, had the drift jumped after the push). Measured case (``tests/test_relocalise.py``,
mixed seed 1, 300 nm at 700 s): a particle pushed into its slot 200 nm below another
slot; the next push of the other particle, made after the jump, shoved the first one
out, and its after-scan took it for the pushed particle, whose slot the report then
named filled by the wrong one.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import shapely
from shapely import affinity

from .context import RunContext
from .engine import Msg
from .scan_steps import locate

#: A correction smaller than this (nm) moves no push's path onto objects that its own
#: quarantine did not already cover (the push's reach, references.QUARANTINE_REACH).
SHOVE_SHIFT = 25.0
#: An object whose footprint comes this close (nm) to a push's corrected swept area
#: may have been shoved by it.
SHOVE_REACH = 10.0


def ambiguous(ctx: RunContext, confirmed: float | None, since: float | None) -> list[str]:
    """Objects seen after the estimate was last confirmed and before the first reference
    it failed (``since``): the drift jumped in between, before or after they were put
    into the layout frame; which, no scan of theirs can tell."""
    if since is None or confirmed is None:
        return []
    return sorted(oid for oid, seen in ctx.belief.seen.items()
                  if confirmed < seen.t < since and oid not in ctx.belief.lost and oid in ctx.belief.objects)


def shoved(ctx: RunContext, confirmed: float | None, shift: np.ndarray, exclude) -> dict[str, str]:
    """Believed particles (not in ``exclude``, not lost) within :data:`SHOVE_REACH` of a
    push made since ``confirmed`` with its swept area moved by the correction
    (``shift``: new less old offset) -> the pushed object of the latest such push."""
    if confirmed is None or math.hypot(*shift) < SHOVE_SHIFT:
        return {}
    belief, out = ctx.belief, {}
    for area in sorted((a for a in ctx.refs.pushes if a.t > confirmed), key=lambda a: a.t):
        g = affinity.translate(area.geometry(), -float(shift[0]), -float(shift[1]))
        x0, y0, x1, y1 = g.bounds
        for oid, o in belief.objects.items():
            if (oid == area.obj or oid in exclude or oid in belief.lost or o.kind != "particle"
                    or oid in ctx.ledger.given_up):
                continue
            far = SHOVE_REACH + o.radius
            x, y = o.at
            if x < x0 - far or x > x1 + far or y < y0 - far or y > y1 + far:
                continue
            if shapely.distance(g, o.geometry()) - o.radius < SHOVE_REACH:
                out[oid] = area.obj
    return out


def recheck(ctx: RunContext, confirmed: float | None, since: float | None, shift: np.ndarray):
    """Locate the objects the jump may have confused (see the module docstring) and keep
    what the scans found. ``shift``: new less old offset. Objects found nowhere are left
    where they were believed, for the next scan of them to search again."""
    seen_between = ambiguous(ctx, confirmed, since)
    displaced = {}                        # shoved object -> the pushed object whose place it took
    for oid, by in sorted(shoved(ctx, confirmed, shift, set(seen_between)).items()):
        found = yield from locate(ctx, oid, widen=False)
        if found is not None:
            _keep(ctx, oid, found)
        elif by in seen_between:
            displaced[oid] = by
            yield Msg("event", (f"{oid} is not where it was believed: the push of {by}, made while the drift "
                                f"jumped, went over it",), {"level": "warn"})
    claimed = {by: oid for oid, by in displaced.items()}
    freed = {}                            # pushed object -> its correction's place, not its own
    for oid in seen_between:
        o = ctx.belief[oid]
        corrected = np.asarray(o.at, float) - shift
        places = [(corrected, "the correction"), (np.asarray(o.at, float), "the old estimate")]
        if oid in claimed:
            places.reverse()              # the correction's place is the displaced object's
        for k, (at, which) in enumerate(places):
            if taken(ctx, oid, at) and which == "the correction":
                continue
            ctx.belief.objects[oid] = replace(o, at=(float(at[0]), float(at[1])))
            found = yield from locate(ctx, oid, widen=k == len(places) - 1)
            if found is not None:
                _keep(ctx, oid, found)
                yield Msg("event", (f"{oid}: seen while the drift jumped; found where {which} put it",))
                if oid in claimed and which == "the old estimate":
                    freed[oid] = corrected
                break
        else:
            ctx.belief.objects[oid] = o
    for oid, by in displaced.items():
        if by not in freed:
            continue
        q = ctx.belief[oid]
        ctx.belief.objects[oid] = replace(q, at=(float(freed[by][0]), float(freed[by][1])))
        found = yield from locate(ctx, oid, widen=False)
        if found is None:
            ctx.belief.objects[oid] = q
            continue
        _keep(ctx, oid, found)
        yield Msg("event", (f"{oid}: found where the push of {by} left what it pushed; {by} was not what "
                            f"its scan after the push saw",), {"level": "warn"})


def _keep(ctx: RunContext, oid: str, found) -> None:
    scanner, cov, t = found[:3]
    seen = ctx.to_layout(scanner, t)
    ctx.observe(oid, seen.at, t, cov, angle=seen.angle)
    ctx.corrected = True


def taken(ctx: RunContext, oid: str, at) -> bool:
    """Whether another believed object (not lost) overlaps ``oid`` placed at ``at`` by
    more than half the smaller's diameter."""
    me = ctx.belief[oid]
    return any(math.dist(o.at, at) < me.radius + o.radius - 0.5 * min(me.diameter, o.diameter)
               for other, o in ctx.belief.objects.items()
               if other != oid and other not in ctx.belief.lost and o.kind == "particle" and me.kind == "particle")
