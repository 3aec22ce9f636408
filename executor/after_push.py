"""What follows a push in the run's loop (:meth:`.assembly.Assembly._pushes`): whether its
object is given up on, whether the rest must be planned again, and correction pushes for an
object its last push left short of its slot. ``asm``: the :class:`~.assembly.Assembly`."""

from __future__ import annotations

import math

from nanoasm.planner import Operation

from . import course as courses
from .engine import Msg


def review(asm, op: Operation, outcome: str, ops: list[Operation], i: int):
    """After the push of ``op`` (``outcome``; ``ops[i:]`` what remains): an object whose
    pushes fail, or leave it far off course, again and again is given up on. Returns why
    the rest must be planned again, or None."""
    ctx, opts, ledger = asm.ctx, asm.options, asm.ctx.ledger
    if outcome == "deferred":                       # not pushed: the rest is planned again first
        ctx.corrected = False
        return f"{op.object} deferred (objects moved by a relocalisation before its push)"
    o = ctx.belief[op.object]
    lost = outcome == "lost"
    off, limit = 0.0, math.inf
    if asm.strategy.scans:
        off = math.inf if lost else math.dist(o.at, op.expect.at)
        limit = courses.off_course_limit(opts, o)
    # an object whose pushes fail, or leave it far off course, again and again
    # (stuck, or against something nobody sees) is not pushed for ever; a rod's
    # course is replanned as a matter of course (its pushes scatter), so for a rod
    # only failed pushes count
    astray_push = outcome == "ok" and off > limit and o.kind != "rod"
    if (outcome == "failed" or astray_push) and ledger.trouble(op.object, opts.max_failures):
        yield Msg("event", (f"gave up on {op.object} after {ledger.troubles[op.object]} pushes "
                            f"failed or went astray: it stays where it is, an obstacle "
                            f"to the rest",), {"level": "warn"})
    if not asm.strategy.scans:
        return None
    astray = o.kind == "rod" and not lost and not courses.course_clear(   # next poses clear?
        o, asm.course.starts, ops[i:], [b for b in asm.ctx.environment().objects if b.id != o.id],
        asm.plan_options.tip_radius)
    moved, ctx.corrected = ctx.corrected, False     # by a relocalisation
    if lost or (asm.strategy.replans and (outcome == "failed" or off > limit or astray or moved)):
        why = ("lost" if lost else f"{off:.0f} nm off course"
               + (", its course now too close to a neighbour" if astray else "")
               + (", objects moved by a relocalisation" if moved else ""))
        return f"{op.object} {outcome} ({why})"
    return None


def correct(asm, op: Operation, ops: list[Operation], i: int, corrections: dict[str, int]) -> None:
    """The last push of ``op``'s object left it short of its slot: correction pushes
    (at most ``max_corrections`` an object) put in at ``ops[i]``."""
    _correct(asm, op.target, op.object, ops, i, corrections)


def _correct(asm, target: str, obj_id: str, ops: list[Operation], i: int, corrections: dict[str, int]) -> None:
    """Correction pushes of ``obj_id`` into slot ``target`` put in at ``ops[i]`` (:func:`correct`)."""
    ctx = asm.ctx
    extra = courses.correction(asm.layout, ctx.belief, target, obj_id, corrections,
                               asm.options.max_corrections, asm.plan_options, max((p.id for p in ops), default=0) + 1)
    if extra is not None:
        ctx.ledger.counts["replans"] += 1
    if extra:
        ops[i:i] = extra
        asm.course.follow(ctx.environment(), extra, extend=True)


def shoved_back(asm, ops: list[Operation], i: int, corrections: dict[str, int]) -> None:
    """Neighbours a push shoved (``RunContext.shoved``, :mod:`.shoves`) that the plan holds
    in a slot and no longer pushes: correction pushes that bring each back within the
    tight tolerance of its slot, put in at ``ops[i]`` (as for a pushed object its last push
    left short, :func:`correct`; none if it is still within it). A shoved object the plan
    still pushes starts its next push from where the scan found it. One found far from
    where it was believed does not make the rest planned again: tried (ae400cd), it lost
    `device` seed 6's rod slot and four particle slots after a replan of the rod that had
    shoved a particle 124 nm, and gained seed 9's s7 (``bench/RESULTS_rods.md``)."""
    ctx = asm.ctx
    shoved, ctx.shoved = ctx.shoved, set()
    plan = asm.replanner.plan or asm.first_plan
    slot = {a.object: a.target for a in plan.assignment}
    for oid in sorted(shoved):
        if oid in slot and oid not in ctx.belief.lost and all(p.object != oid for p in ops[i:]):
            _correct(asm, slot[oid], oid, ops, i, corrections)
