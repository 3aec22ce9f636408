"""The run's verdict on every slot, from check scans at the end: what the report says is
filled is what a scan found there, not what the belief expects.

For each target of the layout, a local scan centred on the slot (the ch. 5 pattern of
its kind, the lines reaching past the position tolerance and the drift estimate's
uncertainty) looks for an object. A slot is ``filled`` when an object of its kind sits
within the layout's tolerance (position, size from the object's height, a rod's angle
and length); otherwise ``missed`` when an object was assigned to it, else ``unfilled``.
``error`` is the measured centre error (nm), None when nothing was found there. An
object found in its slot is observed there (the belief ends as the scans saw it); in a
slot no object is assigned to, the particle found is named where the belief can tell
which it is (:func:`_named`), and the report's assignment then holds it. What
a particle slot's lines find on a believed rod's body is that rod, not a particle (its
thickness would pass the size check); a line that a neighbour's edge cut is tried again,
turned, and a sighting wider than a sphere of its height is no particle. Where a
neighbour the belief does not know of (an object pushed astray and lost) still runs into
the lines, so that they find nothing or something out of the slot, a small image of the
slot tells: each particle's apex, fitted to a fraction of a pixel (:mod:`.apex_check`).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any, NamedTuple

import numpy as np

from nanoasm.cad.layout import Layout

from .apex_check import CROWDED, ROUND, apex_cov, image_check
from .context import RunContext
from .course import tight
from .drift_steps import suspect_drift, take_reference
from .engine import Msg
from .local_scan import particle_before, rod_before
from .scan_steps import clear_direction, run_pattern
from .slot_verdict import STATES, SlotVerdict
from .summary import summary

__all__ = ["STATES", "SlotVerdict", "check_again", "check_slots", "final_check"]

#: Line beyond a particle slot's reach (nm): substrate to level the line on, not so much
#: that it runs into the neighbours of a packed array (150 nm apart).
CHECK_MARGIN = 20.0

def _height_ok(target, height: float, tol) -> bool:
    """Whether a sighting's height is the slot's (a particle's diameter; a rod's thickness)."""
    return abs(height - target.diameter) <= tol.size * target.diameter


def _size_ok(target, res, tol) -> bool:
    """Whether the object a check scan found is of the slot's size: its height and a
    rod's length."""
    peaks = [ln.edges.peak for ln in res.lines if ln.edges.found and ln.edges.peak is not None]
    if peaks and not _height_ok(target, max(peaks), tol):
        return False
    if target.kind == "rod" and res.length is not None:
        return abs(res.length - target.length) <= tol.size * target.length + target.diameter
    return True


#: Turns (degrees) of a particle check's lines tried when a neighbour cut one.
RETRY_TURNS = (45.0, 22.5, 67.5)
#: A particle slot's sighting within this (nm) of a believed rod's body is the rod.
ROD_REACH = 10.0


def _rod_there(ctx: RunContext, at) -> str | None:
    """A believed rod (not lost) whose body covers ``at`` (layout frame) to within
    :data:`ROD_REACH`: a rod crossing a particle slot looks like a particle to two short
    lines (its thickness passes the size check)."""
    import shapely

    p = shapely.Point(float(at[0]), float(at[1]))
    for oid, o in ctx.belief.objects.items():
        if o.kind == "rod" and oid not in ctx.belief.lost \
                and shapely.distance(o.geometry(), p) < o.radius + ROD_REACH:
            return oid
    return None


#: Tip radius (nm) a sighting's widths allow for, and the slack on the widest.
TIP_ALLOWANCE = 12.0
ROUND_SLACK = 1.12


def _round(res) -> bool:
    """Whether what a particle pattern found is as wide as a sphere of its height on
    every line: a rod crossing the slot obliquely is wider on both lines (by 1/sin and
    1/cos of its angle to them, at least √2 on one), a particle on none (a line off
    its centre is narrower)."""
    found = [ln.edges for ln in res.lines if ln.edges.found and ln.edges.peak is not None]
    if not found:
        return True
    r = max(e.peak for e in found) / 2.0 + TIP_ALLOWANCE
    widest = max(e.width for e in found)
    lowest = min(e.level for e in found)
    sphere = 2.0 * math.sqrt(max(r * r - (lowest - r + TIP_ALLOWANCE) ** 2, 0.0))
    return widest <= ROUND_SLACK * sphere


class _Sighting(NamedTuple):
    """What a slot's check saw: the centre (layout frame) at time ``t``, its covariance,
    whether its size is the slot's and whether it is round (a particle, not a ridge)."""

    centre: np.ndarray
    t: float
    cov: np.ndarray | None
    size_ok: bool
    round: bool


def _angle_error(a: float, b: float) -> float:
    d = abs((a - b) % 180.0)
    return min(d, 180.0 - d)


def final_check(asm):
    """The check scans (plan stub, :func:`check_slots`) that set ``asm.slots``:
    of every slot, or after a round that pushed only particles at the edge of their
    slots (``asm.recheck``), of those slots alone."""
    only, asm.recheck = asm.recheck, None
    asm.slots = yield from check_slots(asm.ctx, asm.layout, summary(asm).assignment, only=only,
                                       previous=asm.slots)
    counts = ", ".join(f"{sum(v.state == s for v in asm.slots)} {s}" for s in STATES)
    yield Msg("event", (f"check scans of the {len(asm.slots)} slot(s): {counts}" if only is None else
                        f"check scans of the {len(only)} slot(s) pushed in again; of all {len(asm.slots)}: "
                        f"{counts}",))


def check_slots(ctx: RunContext, layout: Layout, assignment, only=None, previous=None) -> Any:
    """Scan every slot of ``layout`` (plan stub); returns its :class:`SlotVerdict`s in
    the layout's order. ``assignment``: the run's final (target, object) pairs. With
    ``only`` (slot ids), only those slots are scanned and the others keep their verdicts
    of ``previous`` (the last check's, in the layout's order).

    A slot whose assigned object is not found within tolerance may be a slot missed, or
    the drift estimate gone wrong (a jump during the last pushes or these scans): a
    reference is measured at once (:func:`~.drift_steps.suspect_drift`), and if the
    estimate had to be relocalised every slot scanned is scanned again, once. If it
    stood (an estimator that measures references), that slot is scanned again, once:
    the creep of a long travel to it (slots far apart, as when only a few are checked)
    can still put the first lines off the object (``scale300`` seed 8: of ten slots
    micrometres apart checked again, one particle 7.2 nm from its slot not found; a
    second look found it 7.4 nm off)."""
    assigned = {a.target: a.object for a in assignment}
    if only is not None and (previous is None or len(previous) != len(layout.targets)):
        raise ValueError("check_slots: 'only' needs the previous verdict of every slot")
    for again in (False, True):
        out = list(previous) if only is not None else [None] * len(layout.targets)
        todo = [k for k, target in enumerate(layout.targets) if only is None or target.id in only]
        t = yield Msg("clock")
        here = yield Msg("position")
        start = ctx.config.codes_to_nm(np.asarray(here))[:2] - ctx.offset(t)
        held = set(assigned.values())
        for k in tour(start, [layout.targets[k].at for k in todo]):
            target = layout.targets[todo[k]]
            obj = assigned.get(target.id)
            verdict = yield from _check_slot(ctx, target, obj, layout.tolerance, held=held)
            out[todo[k]] = verdict
            if not again and _near_edge(target, verdict, layout):
                out[todo[k]] = yield from _look_again(ctx, target, obj, layout, verdict)
                continue
            if again or verdict.state != "missed":
                continue
            if (yield from suspect_drift(ctx, obj, target.at)):
                yield Msg("event", ("the drift estimate was relocalised during the check scans: "
                                    f"every slot{'' if only is None else ' of these'} is scanned again",),
                          {"level": "warn"})
                break
            if not ctx.drift.uses_landmarks:     # no reference measured: the same look again
                continue
            # the estimate stood: the slot once more, the creep of the travel here settled
            # and the estimate fresh from that reference
            out[todo[k]] = yield from _second_look(ctx, target, obj, layout, f"slot {target.id}")
        else:
            break
    return tuple(out)


def _near_edge(target, verdict, layout: Layout) -> bool:
    """A rod slot the check found filled, but farther from its centre than the tight
    tolerance (:func:`~.course.tight`): a rod's check errs more than a particle's (its
    lines after the travel to it, ends hidden by neighbours), and no repair round pushes a
    rod in as it does a particle at the edge (:mod:`.edge_slots`)."""
    return (target.kind == "rod" and verdict.state == "filled" and verdict.error is not None
            and verdict.error > tight(layout).position)


def _look_again(ctx: RunContext, target, obj: str | None, layout: Layout, first) -> Any:
    """A rod slot :func:`_near_edge`: a drift reference measured near it, then
    :func:`_second_look` (plan stub; without drift references, the second look alone).
    ``rods`` seed 5 on dcdd462: the one look put a shoved rod 16.4 nm from its slot where
    it lay 20.9 nm off. Over ``rods``, ``mixed``, ``device`` and ``rodgap`` (seeds 1-10,
    dcdd462) the error a check measured differed from the true one by up to 10 nm at a
    rod slot (6 nm at the 90th percentile), 6 nm at a particle slot (3.6)."""
    if ctx.drift.uses_landmarks:
        yield from take_reference(ctx, target.at, obj, force=True)
    return (yield from _second_look(ctx, target, obj, layout, f"slot {target.id}: filled {first.error:.1f} nm "
                                    f"off, beyond {tight(layout).position:.0f} nm;"))


def _second_look(ctx: RunContext, target, obj: str | None, layout: Layout, why: str) -> Any:
    """The slot scanned once more, the creep of the travel to it settled (and the estimate
    fresh from a reference, where the run measures them); the second look is the verdict,
    said in an event that begins with ``why`` (plan stub)."""
    second = yield from _check_slot(ctx, target, obj, layout.tolerance)
    after = " after a drift reference" if ctx.drift.uses_landmarks else ""
    yield Msg("event", (f"{why} checked again{after}: {second.state}"
                        + ("" if second.error is None else f" ({second.error:.1f} nm)"),))
    return second


def tour(start, points) -> list[int]:
    """The order (indices into ``points``, layout frame nm) in which the check visits
    them from ``start``: each next the nearest not yet visited (ties by index). In the
    layout's order a grid is checked row by row, and each row's first slot came right
    after a travel back across the whole area: on ``scale1000`` seed 2 the creep of those
    36 µm travels put the lines of all 17 slots of the grid's first column 35 nm and more
    from their particles, and the verdict called them missed, twice."""
    pts = np.asarray(points, float).reshape(-1, 2)
    left = np.ones(len(pts), bool)
    at, order = np.asarray(start, float).reshape(2), []
    for _ in range(len(pts)):
        d = np.where(left, np.hypot(*(pts - at).T), np.inf)
        k = int(np.argmin(d))
        order.append(k)
        left[k] = False
        at = pts[k]
    return order


def check_again(ctx: RunContext, layout: Layout, assignment, verdicts) -> Any:
    """The check scans of the slots not filled by ``verdicts`` (the last check's), again;
    returns every slot's verdicts, the filled ones kept. For a repair round that planned
    no push: its survey found what it looked for where the plan wants it, or moved the
    drift estimate, so the last check scans may have looked in the wrong place (allpushed
    seed 4, a 300 nm jump at 815 s: a slot filled in truth was reported missed, its survey
    found the belief held and planned nothing)."""
    todo = {t.id for t, v in zip(layout.targets, verdicts) if v.state != "filled"}
    if not todo:
        return tuple(verdicts)
    out = yield from check_slots(ctx, layout, assignment, only=todo, previous=verdicts)
    again = [v for t, v in zip(layout.targets, out) if t.id in todo]
    yield Msg("event", (f"check scans of the {len(todo)} slot(s) not filled, again: " +
                        ", ".join(f"{sum(v.state == s for v in again)} {s}" for s in STATES),))
    return out


def _check_slot(ctx: RunContext, target, obj: str | None, tol, held=frozenset()) -> Any:
    """The check scan of one slot (plan stub): its :class:`SlotVerdict`. A slot no object
    is assigned to that the scan finds filled is filled by the object :func:`_named`
    (``held``: the objects other slots are assigned)."""
    t = yield Msg("clock")
    off = ctx.offset(t)
    reach = tol.position + ctx.r_max(t)
    at = np.asarray(target.at, float) + off
    # the lines look for an object of the slot's size: as tall as its size tolerance allows
    wide = replace(ctx.scan_opts, taller=None if ctx.scan_opts.taller is None
                   else max(ctx.scan_opts.taller, 1.0 + tol.size))
    if target.kind == "rod":
        # the lines are placed for the assigned rod's length and tell it by its diameter
        # (placed for the slot's, they crossed beyond the ends of a shorter rod the slot
        # takes); with none assigned, for the slot's, any rod of its size tolerance. The
        # size check below is the slot's.
        length, diameter, opts = target.length, target.diameter, replace(wide, rod_height=tol.size)
        if obj is not None and obj in ctx.belief.objects and ctx.belief[obj].kind == "rod":
            length, diameter, opts = ctx.belief[obj].length, ctx.belief[obj].diameter, wide
        pattern = rod_before(at, target.angle, length, diameter, reach, measure_angle=True, options=opts)
    else:
        # short lines: a slot's neighbours in a packed array are a few tens of nm away
        opts = replace(wide, margin=CHECK_MARGIN)
        half = target.radius + reach + CHECK_MARGIN
        exclude = {obj} if obj is not None else set()
        direction = clear_direction(ctx, np.asarray(target.at, float), half, exclude=exclude)
        pattern = particle_before(at, target.diameter, reach, direction=direction, options=opts)
    res = yield from run_pattern(ctx, pattern)
    for turn in RETRY_TURNS:
        if res.found or target.kind == "rod" or "cut by the line end" not in res.reason:
            break
        # a neighbour at a line's end hid the edge (one the belief does not know of
        # there): again, the lines turned
        c, s_ = math.cos(math.radians(turn)), math.sin(math.radians(turn))
        turned = np.array([c * direction[0] - s_ * direction[1], s_ * direction[0] + c * direction[1]])
        res = yield from run_pattern(ctx, particle_before(at, target.diameter, reach, direction=turned,
                                                          options=opts))
    state, error = ("missed" if obj is not None else "unfilled"), None
    sighting = None
    if res.found:
        t_scan = ctx.scan_ref if ctx.scan_ref is not None else t
        sighting = _Sighting(np.asarray(res.centre, float) - ctx.offset(t_scan), t_scan, res.cov,
                             _size_ok(target, res, tol), target.kind == "rod" or _round(res))
    crowded = any(ln.edges.reason in CROWDED for ln in res.lines)
    if target.kind != "rod" and (crowded if sighting is None else
                                 not sighting.round or crowded and math.dist(sighting.centre, target.at) > tol.position):
        # a neighbour the belief does not know of ran into the lines: they found nothing,
        # stepped aside onto the neighbour, or took two bumps for one (wider than a
        # particle: a rod's body crossing the slot is too). An image of the slot.
        why = (f"its lines ran into a neighbour ({res.reason})" if sighting is None else
               "its lines found something wider than a particle" if not sighting.round else
               "its lines ran into a neighbour and found something out of the slot")
        sighting = (yield from _by_image(ctx, target, reach, tol, why)) or sighting
    if sighting is None and obj is not None:
        yield Msg("event", (f"slot {target.id}: the check scan did not find {obj}: {res.reason}",),
                  {"level": "warn"})
    if sighting is not None:
        centre, t_scan, cov, size_ok, round_ok = sighting
        error = math.dist(centre, target.at)
        good = error <= tol.position and size_ok
        if target.kind == "rod":
            good = good and res.angle is not None and _angle_error(res.angle, target.angle) <= tol.angle
        rod = _rod_there(ctx, centre) if good and target.kind != "rod" else None
        if good and target.kind != "rod" and rod is None and not round_ok:
            good = False
            yield Msg("event", (f"slot {target.id}: the object found is wider across than a particle "
                                f"of its height: an elongated object",), {"level": "warn"})
        if rod is not None:
            yield Msg("event", (f"slot {target.id}: the object found lies on the axis of rod {rod}; "
                                f"not taken for a particle",), {"level": "warn"})
        elif good:
            state = "filled"
            if obj is None and target.kind == "particle":
                obj = yield from _named(ctx, target, centre, (t_scan, cov), tol, held)
        if rod is None and (good or error > tol.position) and obj is not None \
                and obj in ctx.belief.objects and obj not in ctx.belief.lost \
                and math.dist(ctx.belief[obj].at, centre) <= reach + tol.position:
            cov = cov if cov is not None else np.eye(2) * 4.0
            ctx.observe(obj, centre, t_scan, cov, angle=res.angle if target.kind == "rod" else None)
    return SlotVerdict(target.id, obj, state, error)


def _named(ctx: RunContext, target, centre, seen, tol, held) -> Any:
    """The particle an unassigned slot's check found at ``centre`` (layout frame; ``seen``:
    the sighting's time and covariance) is, or None (plan stub): a believed particle of
    the slot's size, assigned to no other slot (``held``), within its search radius of
    the sighting; else the particle of that size the belief has lost, or places on
    another believed particle (one of the two is not there), nearest the sighting within
    the lost-object search's reach (as a survey names what no believed object explains).
    The object is observed there. A jump that struck as a push ended (allpushed seed 1,
    300 nm at 750 s) left a particle in its slot and its after-scan in the stale frame,
    which put it onto its neighbour's place: its slot unassigned by the replan and
    reported filled by no object, the report's assignment one short."""
    t, cov = seen
    fits = [(oid, o) for oid, o in ctx.belief.objects.items()
            if o.kind == "particle" and oid not in held and oid not in ctx.ledger.given_up
            and abs(o.diameter - target.diameter) <= tol.size * target.diameter]
    near = sorted((math.dist(o.at, centre), oid) for oid, o in fits if oid not in ctx.belief.lost
                  and math.dist(o.at, centre) <= ctx.r_max(t, oid) + tol.position)
    doubtful = sorted((math.dist(o.at, centre), oid) for oid, o in fits
                      if math.dist(o.at, centre) <= ctx.options.lost_radius
                      and (oid in ctx.belief.lost or ctx.belief.taken(oid, o.at)))
    if not (near or doubtful):
        return None
    d, oid = (near or doubtful)[0]
    why = ("lost" if oid in ctx.belief.lost else "believed on another particle") if not near else ""
    ctx.belief.lost.discard(oid)
    ctx.observe(oid, centre, t, cov if cov is not None else np.eye(2) * 4.0)
    yield Msg("event", (f"slot {target.id}: filled by {oid}, no slot's object, " + (
        f"{why}, {d:.0f} nm from where it was last believed" if why else f"{d:.0f} nm from where it was believed"),),
              {"level": "warn"})
    return oid


def _by_image(ctx: RunContext, target, reach: float, tol, why: str) -> Any:
    """A particle slot's check by a small image (:mod:`.apex_check`), when its lines
    could not tell (``why``; plan stub): (centre in the layout frame, time, covariance,
    size ok, round) of the round apex nearest the slot (a ridge's where there is none),
    or None where no apex lies within reach."""
    got = yield from image_check(ctx, target.at, target.diameter, reach, f"slot {target.id}")
    if got is None:
        return None
    apices, pixels = got
    near = [(a, at, t) for a, at, t in apices if math.dist(at, target.at) <= reach]
    if not near:
        yield Msg("event", (f"slot {target.id}: {why}; an image of {pixels} x {pixels} px shows no "
                            f"particle within {reach:.0f} nm",),
                  {"level": "warn"})
        return None
    a, at, t = min(near, key=lambda n: (n[0].roundness < ROUND, math.dist(n[1], target.at)))
    size_ok = _height_ok(target, a.height, tol)
    yield Msg("event", (f"slot {target.id}: {why}; an image of {pixels} x {pixels} px shows "
                        + ("a particle" if a.roundness >= ROUND else "a ridge, no particle,")
                        + f" {math.dist(at, target.at):.1f} nm from it, {a.height:.0f} nm high",))
    return _Sighting(at, t, apex_cov(ctx, a), size_ok, a.roundness >= ROUND)
