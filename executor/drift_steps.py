"""Drift measurements as plan stubs: a reference scanned before a push, a pushed object's
own scan folded in while it is still a reference, and the drift velocity from the full
scan's skew.

Free generator functions over a :class:`~nanoasm.executor.context.RunContext`; what to
measure and what a measurement means is the drift estimator's
(:mod:`nanoasm.executor.estimators`).
"""

from __future__ import annotations

import numpy as np

from .context import RunContext
from .engine import Msg
from .scan_steps import locate

#: Objects scanned again to find the drift velocity from the full scan's skew.
BOOTSTRAP_OBJECTS = 4


def emit_drift(ctx: RunContext, t: float):
    """Emit the drift estimate (for the estimators that have one to tell)."""
    if ctx.drift.emits:
        yield Msg("emit", ("drift", ctx.drift.doc(t)))


def fold(ctx: RunContext, obj_id: str, scanner_at, cov, t: float, *, reference: bool = False) -> bool:
    """Fold a measured position (scanner frame) of ``obj_id`` into the drift estimate, if
    it measures drift (``reference``: the reference the estimator chose); False only when
    the estimate's gate rejected it (it moved on its own)."""
    measure = ctx.drift.measure_reference if reference else ctx.drift.measure
    folded = measure(obj_id, scanner_at, cov, t, ctx.refs, ctx.ledger.pushed, ctx.belief.lost)
    if folded is not None:
        ctx.log_drift(t)
    return folded is not False


def take_reference(ctx: RunContext, near, obj_id: str | None = None):
    """Measure drift on the reference the estimator wants before a push of ``obj_id``
    near ``near`` (an untouched object, the anchor, or none)."""
    t = yield Msg("clock")
    ref = ctx.drift.reference_target(t, near, obj_id, ctx.belief, ctx.refs, ctx.ledger.pushed,
                                     ctx.moving, ctx.options)
    if ref is None:
        return
    found = yield from locate(ctx, ref)
    if found is None:
        if ctx.drift.references_are_objects:
            ctx.belief.lose(ref)
        return
    body, cov, t, _ = found
    if not fold(ctx, ref, body.at, cov, t, reference=True):
        yield Msg("event", (f"{ref} moved on its own (gated out of the drift estimate)",), {"level": "warn"})
    yield from emit_drift(ctx, t)
    if ctx.drift.references_are_objects:
        ctx.observe(ref, ctx.to_layout(body, t).at, t, cov)


def bootstrap(ctx: RunContext):
    """The drift velocity from the full scan's own distortion (estimators that want it).

    A full scan takes minutes: an object on row ``i`` was imaged at ``τ_i`` and the
    identified position carries the drift ``o(τ_i)``. Scanning a few objects again
    from bottom to top rows gives ``z_i = o(t_i) − o(τ_i) = v (t_i − τ_i)``: the velocity
    by least squares, which starts the drift filter (and corrects every other object
    of the first scan for its row's drift).
    """
    drift, belief = ctx.drift, ctx.belief
    if not drift.bootstraps:
        return
    cands = sorted((o for o in belief.objects.values() if o.kind == "particle" and not o.edge),
                   key=lambda o: belief.seen[o.id].t)
    if len(cands) < 2:
        return
    k = min(BOOTSTRAP_OBJECTS, len(cands))
    picks = [cands[round(j * (len(cands) - 1) / (k - 1))] for j in range(k)]
    # latest rows first: their drift since is the smallest, so their lines are short,
    # and every one sharpens the velocity that sizes the next one's lines
    picks.sort(key=lambda o: -belief.seen[o.id].t)
    rows = []
    for o in picks:
        found = yield from locate(ctx, o.id)
        if found is None:
            continue
        body, cov, t, _ = found
        # o(t) - o(τ) less the creep the moves made so far are modelled to cause
        z = np.asarray(body.at) - drift.origin - np.asarray(o.at) - drift.creep_offset(t - drift.epoch)
        rows.append((o.id, body, cov, t, z, t - belief.seen[o.id].t))
        dts = np.array([r[5] for r in rows])
        zs = np.array([r[4] for r in rows])
        v = (zs * dts[:, None]).sum(axis=0) / float((dts ** 2).sum())
        resid = zs - dts[:, None] * v[None, :]
        var = (float(np.mean(resid ** 2)) if len(rows) > 2 else 25.0) + 4.0
        drift.restart(v, var / float((dts ** 2).sum()))
    if not rows:
        return
    for oid, body, cov, t, _, _ in rows:
        ctx.observe(oid, ctx.to_layout(body, t).at, t, cov)
    v = drift.velocity()
    yield Msg("event", (f"drift from the full scan's skew: {v[0]:+.3f}, {v[1]:+.3f} nm/s "
                        f"(+/- {drift.velocity_std():.3f}) from {len(rows)} objects",))
    ctx.log_drift(rows[-1][3])
    yield from emit_drift(ctx, rows[-1][3])
