"""Pushes of several particles in one contact phase (issue 16: less dead time).

A push is made in contact mode and its scans in tapping mode; the instrument switches
between the two (``TimingParams.mode_switch``, 2 s on the simulator) into contact before
every push and back before the scan after it. Those two switches a push were about half of
the instrument time above the physical bound on the particle families (``bench/RESULTS.md``).

With ``ExecOptions.contact_batch = n > 1``, the pushes of up to ``n`` particles that cannot
touch one another are made in one contact phase: each located by its scan before (all in
one tapping phase), pushed one after another, then each scanned after (the next tapping
phase): two switches for the group instead of two a push.

Which pushes go together (:func:`together`): from the next push on, each further particle's
push whose area, swept by the tip and the particle from where it is believed to where the
plan expects it (:func:`~.references.swept_area`), stays at least ``replan_after`` from the
area of every push it is brought forward over or grouped with (an object's later push starts
where it is believed, inside its earlier push's area: only its next push can go).
A push the plan ordered after another because that one clears its way sweeps across the
other's area, so it is never brought forward; a particle that strays by less than
``replan_after`` (beyond which the rest is planned again) does not reach another's area.
Two straying toward each other by more than half of it each could touch: their scans after
see both off course, and the rest is planned again.
Rods are pushed one at a time (their scans after feed the pivot filter, and the next push
is chosen from them).

The scans before a group (and a failed push's drift check) may revise the drift estimate
between a particle's scan and its push: an object not yet pushed is a drift reference. Each
measurement folded in meanwhile shifts the offset the estimate gives at its own time (new less
old, :class:`_Revisions`); a particle's believed position, put into the layout frame by the
estimate of its scan, is moved back by the shifts since, just before its push, as a push right
after its own scan would have it (the velocity's revision over the seconds between is left
out). A relocalisation moves the beliefs it concerns itself (``relocalise._correct_beliefs``).
A push never starts from its last after-scan without a scan in a group (``trust_after_scan``).
"""

from __future__ import annotations

import inspect
import numpy as np
import shapely

from nanoasm.bodies import Body
from nanoasm.planner import Operation, PlanOptions

from .context import RunContext
from .engine import Msg
from .pushing import aim, conclude, deferred, prepare, press
from .references import swept_area

#: Pushes looked ahead over for partners of the next one.
LOOKAHEAD = 24


def _area(ctx: RunContext, op: Operation, at, tip_radius: float) -> shapely.Polygon:
    """What the push ``op`` may sweep: its tip path widened by the tip, its object where
    believed (``at``) and where the plan expects it."""
    o = ctx.belief[op.object]
    start = Body(o.id, o.kind, tuple(at), o.diameter, o.angle, o.length)
    end = Body(o.id, o.kind, op.expect.at, o.diameter, o.angle if op.expect.angle is None else op.expect.angle,
               o.length)
    return shapely.Polygon(swept_area(op.object, 0.0, op.tip_path, [start, end], tip_radius=tip_radius).ring)


def together(ctx: RunContext, ops: list[Operation], i: int, plan_options: PlanOptions) -> int:
    """How many pushes from ``ops[i]`` on to make in one contact phase (see the module
    docstring); the partners are moved up to follow ``ops[i]`` in ``ops`` (in place), so the
    group is ``ops[i:i + n]``. 1 (and ``ops`` untouched) when nothing goes with it."""
    limit = ctx.options.contact_batch
    belief = ctx.belief
    if limit <= 1 or not ctx.options.strategy.scans or belief[ops[i].object].kind != "particle":
        return 1
    window = ops[i:i + LOOKAHEAD]
    ids = sorted({op.object for op in window})
    where = dict(zip(ids, ctx.positions(ids)))
    areas: list[shapely.Polygon] = []

    def area(j: int) -> shapely.Polygon:        # made as the look ahead reaches it (it stops at the limit)
        while len(areas) <= j:
            op = window[len(areas)]
            areas.append(_area(ctx, op, where[op.object], plan_options.tip_radius))
        return areas[j]

    margin = ctx.options.replan_after
    members = [0]
    for j in range(1, len(window)):
        op = window[j]
        if len(members) == limit:
            break
        if op.object in belief.lost or belief[op.object].kind != "particle":
            continue
        # (a later push of an object starts where it is believed, inside its earlier
        # push's area: never brought forward over it, nor grouped with it)
        if all(area(j).distance(area(k)) >= margin for k in range(j)):
            members.append(j)
    if len(members) == 1:
        return 1
    chosen = [window[j] for j in members]
    rest = [op for j, op in enumerate(window) if j not in members]
    ops[i:i + len(window)] = chosen + rest
    return len(chosen)


class _Revisions:
    """The drift estimator as it is, but for the measurements folded into it: each adds
    to ``shift`` what it moved the offset at its own time by (new less old)."""

    WATCHED = ("measure", "measure_reference", "measure_feature")

    def __init__(self, est):
        object.__setattr__(self, "est", est)
        object.__setattr__(self, "shift", np.zeros(2))

    def __setattr__(self, name: str, value) -> None:
        if name == "shift":
            object.__setattr__(self, name, value)
        else:                                   # the estimator's own attributes stay its own
            setattr(self.est, name, value)

    def __getattr__(self, name: str):
        method = getattr(self.est, name)
        if name not in self.WATCHED:
            return method

        def watched(*args, **kwargs):
            est = self.est
            t = est.clamp(float(inspect.signature(method).bind(*args, **kwargs).arguments["t"]))
            before = np.asarray(est.offset(t), float)
            out = method(*args, **kwargs)
            self.shift = self.shift + np.asarray(est.offset(est.clamp(t)), float) - before
            return out
        return watched


def _follow(ctx: RunContext, obj_id: str, shift: np.ndarray) -> None:
    """``obj_id``'s believed position moved back by the estimate's ``shift`` since its scan."""
    if np.any(shift != 0.0) and obj_id not in ctx.belief.lost:
        ctx.belief.reframe(obj_id, shift)


def push_together(ctx: RunContext, group: list[Operation], course, lever, plan_options: PlanOptions):
    """The pushes of ``group`` in one contact phase: each object located (tapping), each
    pushed (contact), each scanned after (tapping). Returns each push's outcome, "ok",
    "failed", "lost" or "deferred" (:func:`~.pushing.deferred`: none is pushed), in the
    group's order."""
    est = ctx.drift
    watch = ctx.drift = _Revisions(est)
    corrected = ctx.corrected
    try:
        ready, seen = [], []
        for op in group:
            ready.append((yield from prepare(ctx, op, plan_options, trust=False)))
            seen.append(watch.shift.copy())
        if (yield from deferred(ctx, corrected, [op for op, lost in zip(group, ready) if lost is None])):
            return [lost or "deferred" for lost in ready]
        names = ", ".join(op.object for op in group)
        yield Msg("event", (f"{len(group)} pushes in one contact phase: {names}",))
        pressed = []
        for op, lost, shift in zip(group, ready, seen):
            if lost is not None:
                pressed.append(lost)
                continue
            _follow(ctx, op.object, watch.shift - shift)
            aimed = aim(ctx, op, course, plan_options)
            if aimed is None:
                pressed.append("ok")
                continue
            done = yield from press(ctx, *aimed, course, lever, plan_options)
            pressed.append(done if isinstance(done, str) else (*done, aimed[1]))
    finally:
        ctx.drift = est
    outcomes = []
    for k, done in enumerate(pressed):
        if isinstance(done, str):
            outcomes.append(done)
            continue
        verdict, op, start = done
        pending = {p.object for p in group[k + 1:]}     # believed where they were before their pushes
        outcomes.append((yield from conclude(ctx, op, start, verdict, course, plan_options, pending)))
    return outcomes
