"""One push with its scans, as a plan stub: a drift reference, a local scan before (the push
re-aimed at where the object really is), the push streamed and watched, a local scan
after, and the verdict."""

from __future__ import annotations

import math

import numpy as np
import shapely

from nanoasm.bodies import Body
from nanoasm.errors import InstrumentLimitError
from nanoasm.planner import Expect, Operation, PlanOptions
from nanoasm.world.cantilever import Cantilever

from .contact_load import ContactModel, needed_normal_force, push_point, push_preload
from .context import RunContext
from .course import Course
from .drift_steps import emit_drift, fold, suspect_drift, take_reference
from .engine import Msg
from .guard_line import guard
from .monitor import Verdict
from .motion_steps import stream_push
from .push_legs import push_in_legs
from .reaim import particle_push, rod_push
from .references import swept_area, within_reach
from .relocalise import keep_track
from .scan_steps import locate, scan_after
from .shoves import after_push

#: A push planned longer than this (nm) that moved its object less than
#: :data:`SLIP_SHARE` of the way left it where it was: the tip slipped over it.
SLIP_MIN_PUSH = 20.0
SLIP_SHARE = 0.25


def _lost(ctx: RunContext, obj_id: str) -> None:
    ctx.belief.lose(obj_id)
    ctx.ledger.fail(obj_id, "lost")


def _locate_start(ctx: RunContext, obj_id: str):
    """Locate the object about to be pushed and fold it into the drift estimate while it
    is a reference. Not where the estimate puts it, the drift is checked first (it may
    have jumped: :func:`~.drift_steps.suspect_drift`), then it is searched for; a fold
    that sets off a relocalisation has it located again where the new estimate puts it.
    Returns (scanner pose, cov, t) or None (not found)."""
    found = yield from locate(ctx, obj_id, widen=False)
    relocalised = False
    if found is None:
        relocalised = yield from suspect_drift(ctx, obj_id, ctx.belief[obj_id].at)
        found = yield from locate(ctx, obj_id)
    if found is None:
        return None
    measured, cov, t, res = found
    if not fold(ctx, obj_id, measured.at, cov, t, scan=res):
        yield Msg("event", (f"{obj_id} moved on its own ({ctx.refs.note(obj_id)})",), {"level": "warn"})
    yield from emit_drift(ctx, t)
    if not relocalised and (yield from keep_track(ctx)):
        found = yield from locate(ctx, obj_id)
    return None if found is None else found[:3]


def _fresh(ctx: RunContext, obj_id: str):
    """Whether the push of ``obj_id`` may start from its belief without a scan: the last
    push's after-scan located it at most ``trust_after_scan`` ago, nothing was pushed
    since, and no measurement revised the drift estimate since (a reference or a
    relocalisation in between would leave the belief in the old estimate's frame)."""
    last = ctx.last_after
    if last is None or ctx.options.trust_after_scan <= 0 or not ctx.options.strategy.kalman:
        return False
    seen_id, t, revision, pushes = last
    if seen_id != obj_id or pushes != ctx.ledger.counts["pushes"] or revision != ctx.drift.revision():
        return False
    now = yield Msg("clock")
    if now - t > ctx.options.trust_after_scan:
        return False
    yield from emit_drift(ctx, now)          # the estimate this push goes by, as a scan's would be
    return True


#: The contact mechanics the preload is chosen by: the seed's nominal values (contact_load).
CONTACT = ContactModel()


def _load_factor(ctx: RunContext, body: Body, op: Operation, lever: Cantilever, tip_radius: float) -> float:
    """The preload, as a multiple of the instrument's, that keeps the tip down on ``body``
    through ``op`` (:mod:`.contact_load`): a rod at the push point nearest its middle of
    where the push starts and where it is expected to end."""
    sigmas = ctx.options.slip_sigmas
    if sigmas < 0:
        return 1.0
    path = op.tip_path
    if body.kind == "rod":
        end = Body(body.id, "rod", op.expect.at, body.diameter,
                   body.angle if op.expect.angle is None else op.expect.angle, body.length)
        ls = [push_point(body, path[0]), push_point(end, path[-1])]
        force = max(needed_normal_force(body, tip_radius, CONTACT, sigmas, l) for l in ls)
    else:
        force = needed_normal_force(body, tip_radius, CONTACT, sigmas)
    cfg = ctx.config
    return push_preload(force, cfg, lever) / cfg.preload


def _quarantine(ctx: RunContext, op: Operation, poses, plan_options: PlanOptions, t: float) -> None:
    """The push of ``op`` may have shoved what lies near its sweep (``poses``: where its
    object started and went, and where the plan expected it): quarantine those."""
    expect = op.expect
    o = ctx.belief[op.object]
    end = Body(o.id, o.kind, expect.at, o.diameter, expect.angle if o.elongated else None,
               o.length if o.elongated else None)
    area = swept_area(op.object, t, op.tip_path, [*poses, end], tip_radius=plan_options.tip_radius)
    ctx.refs.pushed_near(area, ctx.belief)


def _beyond_range(ctx: RunContext, obj_id: str, error: InstrumentLimitError):
    """A push whose path, with the drift predicted over it, leaves the scanner's range
    (nothing of it was sent): the drift has carried the object, or where it is to go,
    out of the tip's reach. The object is given up, an obstacle where it is; the drift
    goes on the same way, so trying it again would fail again."""
    ledger = ctx.ledger
    ledger.counts["failed_pushes"] += 1
    ledger.fail(obj_id, "out of range")
    ledger.given_up.add(obj_id)
    yield Msg("event", (f"gave up on {obj_id}: its push would leave the scanner's range ({error}); "
                        f"it stays where it is, an obstacle to the rest",), {"level": "error"})


def prepare(ctx: RunContext, op: Operation, plan_options: PlanOptions, *, trust: bool = True):
    """Everything before a push in tapping mode: drift references, and its object located
    (or, with ``trust``, taken from its last after-scan: :func:`_fresh`). Returns None, or
    "lost" (not found)."""
    obj_id = op.object
    if not ctx.options.strategy.scans:
        return None
    start = ctx.belief[obj_id]
    yield from keep_track(ctx)
    yield from take_reference(ctx, start.at, obj_id)
    yield from keep_track(ctx)
    fresh = trust and (yield from _fresh(ctx, obj_id))
    if fresh:                   # one line checks the after-scan still holds
        heading = np.asarray(op.expect.at, float) - np.asarray(start.at, float)
        why = yield from guard(ctx, obj_id, heading, plan_options.tip_radius)
        if why is not None:
            fresh = False
            yield Msg("event", (f"{obj_id}: its after-scan not confirmed ({why}); scanning it",),
                      {"level": "warn"})
    if fresh:
        return None
    found = yield from _locate_start(ctx, obj_id)
    if found is None:
        _lost(ctx, obj_id)
        yield Msg("event", (f"{obj_id} lost: not found within {ctx.options.lost_radius:.0f} nm",),
                  {"level": "error"})
        _quarantine(ctx, op, [start], plan_options, (yield Msg("clock")))
        return "lost"
    measured, cov, t = found
    measured = ctx.to_layout(measured, t)       # with the drift as now estimated
    ctx.observe(obj_id, measured.at, t, cov, angle=measured.angle)
    if ctx.belief[obj_id].kind == "rod":
        ctx.pivots.seen(ctx.belief[obj_id], cov)
    return None


def aim(ctx: RunContext, op: Operation, course: Course, plan_options: PlanOptions):
    """The push ``op`` re-aimed at where its object is believed: (operation, start pose),
    or None (a particle already where the push would leave it)."""
    start = ctx.belief[op.object]
    if not ctx.options.strategy.scans:
        return op, start
    if start.kind == "rod":
        at, angle = course.starts.get(op.id, (start.at, start.angle))
        expected = Body(op.object, "rod", at, start.diameter, angle, start.length)
        return rod_push(op, expected, start), start
    op = particle_push(op, start.at, start.radius, plan_options.tip_radius, plan_options.lead)
    return None if op is None else (op, start)


def press(ctx: RunContext, op: Operation, start, course: Course, lever: Cantilever, plan_options: PlanOptions):
    """The push itself, in contact mode, its signals watched: (verdict, operation as
    the model now expects it), or "ok" (a particle already there) or "failed" (out of
    the scanner's range)."""
    obj_id = op.object
    scans = ctx.options.strategy.scans
    # pressed to keep the tip down on this object, harder again for each slip over it
    preload = course.preload.get(obj_id, 1.0) * _load_factor(ctx, start, op, lever, plan_options.tip_radius)
    try:
        if scans and start.kind == "particle":      # long pushes in legs, a line across between
            verdict, legs, _ = yield from push_in_legs(ctx, op, start, lever, preload, plan_options.tip_radius,
                                                      plan_options.lead)
            if verdict is None:
                return "ok"
        else:
            verdict, legs = (yield from stream_push(ctx, op, lever, preload)), 1
    except InstrumentLimitError as e:
        yield from _beyond_range(ctx, obj_id, e)
        return "failed"
    ledger = ctx.ledger
    ledger.counts["pushes"] += legs
    ledger.pushed_once(obj_id)
    if scans and start.kind == "rod" and not verdict.failed:    # the model with this rod's pivot
        pose = ctx.pivots.pushed(obj_id, op.tip_path, plan_options.tip_radius)
        op = Operation(op.id, op.object, op.target, op.tip_path, Expect(pose.at, pose.angle), op.kind)
    if not verdict.failed:
        ctx.belief.expect(obj_id, op.expect.at, op.expect.angle)
    else:                       # the tip lost it: believed where it was last seen (the last leg's start)
        ledger.counts["failed_pushes"] += 1
        ledger.fail(obj_id, verdict.status)
        yield Msg("event", (f"push of {obj_id} {verdict.status} (peak force {verdict.peak_force:.0f} nN)",),
                  {"level": "warn"})
        if scans:
            # the tip lost its object: perhaps the drift jumped under it, so references
            # first. The lost object itself is no evidence of a jump (on scale1000 seed 3,
            # 207 slips; counted, it and one reference the slipped particle shoved made two
            # in a row; 28 relocalisations of 250 s, most to a window 12-34 nm off)
            yield from suspect_drift(ctx, obj_id, op.expect.at, count=False)
    return verdict, op


def conclude(ctx: RunContext, op: Operation, start, verdict: Verdict, course: Course, plan_options: PlanOptions,
             pending=()):
    """After the push, in tapping mode: where did the object go (the scan after it), the
    neighbours it shoved (:mod:`.shoves`; ``pending``: objects pushed whose scans after are
    still to come) and the push's record. Returns "ok", "failed" or "lost"."""
    obj_id, ledger = op.object, ctx.ledger
    if ctx.options.strategy.scans:
        after = yield from scan_after(ctx, op, start)
        if after is None:
            yield from suspect_drift(ctx, obj_id, op.expect.at)
            located = (yield from _where_it_was(ctx, op)) if verdict.failed else None
            if located is None:
                located = yield from locate(ctx, obj_id)
            if located is None:
                _lost(ctx, obj_id)
                _quarantine(ctx, op, [start], plan_options, (yield Msg("clock")))
                return "lost"
            scanner, cov, t = located[:3]
            after = (ctx.to_layout(scanner, t), cov, t)
        body, cov, t = after
        ctx.observe(obj_id, body.at, t, cov, angle=body.angle)
        planned = math.dist(start.at, op.expect.at)
        if not verdict.failed and planned > SLIP_MIN_PUSH and math.dist(start.at, body.at) < SLIP_SHARE * planned:
            # the signals missed it, the scans did not: the tip went over the object
            verdict = Verdict("slipped", None, verdict.peak_force)
            ledger.counts["failed_pushes"] += 1
            ledger.fail(obj_id, "slipped")
            yield Msg("event", (f"push of {obj_id} left it where it was: slipped over",), {"level": "warn"})
        if verdict.status == "slipped":
            course.slipped(obj_id)
        if body.kind == "rod":
            (ctx.pivots.restart if verdict.failed else ctx.pivots.seen)(body, cov)
        ctx.last_after = [obj_id, float(t), ctx.drift.revision(), ledger.counts["pushes"]]
        yield from after_push(ctx, op, body, pending)
    t_end = yield Msg("clock")
    _quarantine(ctx, op, [start, ctx.belief[obj_id]], plan_options, t_end)
    doc = {"op": op.to_dict(), "verdict": verdict.status, "t": t_end,
           "offset": [float(v) for v in ctx.offset(t_end)], "before": [float(v) for v in start.at],
           "peak_force": verdict.peak_force, "belief": ctx.belief[obj_id].to_dict()}
    if obj_id in ctx.pivots.rods:
        doc["pivot"] = ctx.pivots.rods[obj_id].to_dict()
    yield Msg("emit", ("push", doc))
    return "failed" if verdict.failed else "ok"


def _where_it_was(ctx: RunContext, op: Operation):
    """An object the tip lost (slipped over, stuck, no contact) that the scan after did not
    find is looked for where it was last seen (the push leaves the belief there: the push's
    start, or the start of the leg that lost it), then believed where the push meant it to
    be if it is not there (the widening search about that follows). The scan after a long
    push looks about its end first and stops at what it finds there: on wide seed 7 a
    neighbour 300 nm from the end of a 3.9 um push the tip had slipped off at once, so the
    search went on about the end, 3.9 um from the particle."""
    located = yield from locate(ctx, op.object, widen=False)
    if located is None:
        ctx.belief.expect(op.object, op.expect.at, op.expect.angle)
    return located


def push(ctx: RunContext, op: Operation, course: Course, lever: Cantilever, plan_options: PlanOptions):
    """One push with its scans; returns "ok", "failed", "lost" or "deferred" (:func:`deferred`)."""
    corrected = ctx.corrected
    if (yield from prepare(ctx, op, plan_options)) == "lost":
        return "lost"
    if (yield from deferred(ctx, corrected, [op])):
        return "deferred"
    aimed = aim(ctx, op, course, plan_options)
    if aimed is None:
        return "ok"
    pressed = yield from press(ctx, *aimed, course, lever, plan_options)
    if isinstance(pressed, str):
        return pressed
    verdict, op = pressed
    return (yield from conclude(ctx, op, aimed[1], verdict, course, plan_options))


#: Times one object's push may wait for a replan (:func:`deferred`): in mixed seed 1, torn at
#: 250 s, relocalisation windows disagree, each deferral's replan met another relocalisation,
#: and four pushes in a row waited (cf20f5e, where any relocalisation deferred).
MAX_DEFERRALS = 1


def in_the_way(ctx: RunContext, op: Operation, others) -> str | None:
    """One of ``others`` (``(id, body)`` pairs: believed objects where the planner would
    put them) that the particle of ``op`` would meet going straight from where it is
    believed to where the push is to leave it: its id, or None. (A rod's course has its
    own check after each push, :func:`~.course.course_clear`.)"""
    o = ctx.belief[op.object]
    if o.kind != "particle":
        return None
    start, end = np.asarray(o.at, float), np.asarray(op.expect.at, float)
    path = shapely.LineString([start, end]) if math.dist(start, end) > 1e-6 else shapely.Point(start)
    hits = within_reach(path, others, o.radius)
    return hits[0] if hits else None


def deferred(ctx: RunContext, corrected: bool, ops):
    """Whether the pushes of ``ops`` (just located) wait for the rest to be planned again
    (plan stub): a relocalisation while they were prepared moved believed objects
    (``ctx.corrected``, False before: ``corrected``), and one now lies in the way of a push
    (:func:`in_the_way`), at most :data:`MAX_DEFERRALS` times an object. The plan was made
    where the objects were believed before. allpushed seed 7, a 300 nm jump at 750 s, pushes
    one at a time (cc0d2b6): o8's after-scan saw it 298 nm off course, the replan gave its
    slot s8 to o9, the relocalisation during o9's before-scan put o8 back into s8, and o9 was
    pushed into s8 all the same, shoving o8 out unseen; the report named the particles of s4
    and s8 the wrong way round."""
    if corrected or not ctx.corrected or not ctx.options.strategy.replans:
        return False
    skip = {op.object for op in ops}
    others = [(b.id, b) for b in ctx.environment().objects if b.id not in skip]    # none lost
    for op in ops:
        if ctx.deferrals.get(op.object, 0) >= MAX_DEFERRALS:
            continue
        other = in_the_way(ctx, op, others)
        if other is not None:
            ctx.deferrals[op.object] = ctx.deferrals.get(op.object, 0) + 1
            names = ", ".join(p.object for p in ops)
            yield Msg("event", (f"{names}: not pushed yet: a relocalisation put {other} in the way of "
                                f"{op.object}'s push, the rest is planned again first",), {"level": "warn"})
            return True
    return False
