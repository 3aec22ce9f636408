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
to, had the drift jumped after the push). Cases: allpushed seed 3, 300 nm at 815 s
(``tests/test_relocalise.py``): a jumped push shoved a particle 60 nm out of its slot,
where the correction put the pushed one; looked for first, it is found there.
``tests/test_association.py``: the shoved particle is gone from where it was believed,
and the pushed one is found where it was believed, the shoved one where the correction
put it. (Mixed seed 1 at 700 s, with the rod change fec0605 that is not landed: the
report had named a slot filled by the wrong particle.)
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from shapely import affinity

from .context import RunContext
from .engine import Msg
from .references import within_reach
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
        candidates = ((oid, o) for oid, o in belief.objects.items()
                      if o.kind == "particle" and oid != area.obj and oid not in exclude
                      and oid not in belief.lost and oid not in ctx.ledger.given_up)
        for oid in within_reach(g, candidates, SHOVE_REACH):
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
            if which == "the correction" and ctx.belief.taken(oid, at):
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

