"""The drift bootstrap: the drift the first full scan's rows carried, measured by scanning a
few of its objects and fixed features again (:func:`bootstrap`), with the references the
others contradict left out (:mod:`~nanoasm.executor.scan_consensus`) and a jump of the
drift during the scan or after it told from velocity (:mod:`~nanoasm.executor.scan_jump`).
"""

from __future__ import annotations

import math

import numpy as np

from nanoasm.drift import gate_threshold

from . import bootstrap_confirm, bootstrap_picks, creep_terms, keepout_frame, tear_doubles
from .context import RunContext
from .drift_steps import emit_drift, scan_feature_lines
from .engine import Msg
from .bootstrap_tear import jump_state, jumped as _jumped, narrow_tear, tear_or_jump, told_again
from .scan_consensus import left_out
from .scan_jump import jump_text
from .scan_steps import locate

#: Objects scanned again to find the drift velocity from the full scan's skew.
BOOTSTRAP_OBJECTS = 4
#: Twice as many where the creep time constant's prior uncertainty moves one side of the
#: area against the other by more than this (nm, 1σ: ``c σ_λ side / ln 10``, twice a
#: located centre's own): its error offsets a reference in proportion to where it lies,
#: which four references along the rows take for velocity (wide, 16 µm, seeds 1-10: λ at
#: the run's end 0.10 from the truth with four, 0.06 with eight, medians); on a 4 µm area
#: it is 3.5 nm, on 5 µm 4.3.
TAU_SPREAD = 4.0
#: Rounds of the bootstrap's outlier test: each leaves out the fewest references (up to
#: :data:`BOOTSTRAP_LEFT_TOGETHER`) whose removal leaves the others consistent within
#: :data:`BOOTSTRAP_GATE` (:func:`~nanoasm.executor.scan_consensus.left_out`), and
#: replaces each by the next pick.
BOOTSTRAP_OUTLIERS = 3
#: References a round may leave out together.
BOOTSTRAP_LEFT_TOGETHER = 2
#: Gate probability of that test (χ² of a reference against the others' model).
BOOTSTRAP_GATE = 0.9999
#: More references :func:`_earliest_rows` may scan for the drift since the scan began.
EARLY_REFERENCES = 2
#: Variance (nm²) of a component a bootstrap reference measures: the located centre's
#: and the full scan's (2 nm each), and what the model leaves (the random walk, creep).
BOOTSTRAP_VAR = 16.0


def _tau_spread(ctx: RunContext) -> float:
    """How far (nm, 1σ) the creep time constant's prior uncertainty moves one side of the
    area against the other: ``c σ_λ side / ln 10``."""
    creep = ctx.drift.params.creep
    return creep.amplitude * creep.tau_std * max(ctx.belief.area) / math.log(10.0)


def bootstrap(ctx: RunContext, keep=None):
    """The drift the full scan's rows carried, from the full scan's own distortion
    (estimators that want it).

    A full scan takes minutes: an object on row ``i`` was imaged at ``τ_i`` and the
    identified position carries the drift ``D(τ_i)``. Scanning a few objects (or fixed
    features) again gives ``z_i = D(t_i) − D(τ_i)`` (a straight edge: its component
    along the edge's normal), linear in the drift's velocity and its steady change
    (:class:`~nanoasm.executor.scan_drift.ScanDrift`): measured by Bayesian least
    squares, they start the drift filter and take every other object of the first scan
    out of its row's drift. Each reference sharpens the model that sizes the next one's
    lines; the variance of a measured component is taken as :data:`BOOTSTRAP_VAR` plus the
    located position's own (which holds what the lines' creep compensation may err by).
    The model holds the creep's time constant's error too (``λ``, each row's dependence
    on it ``CreepHistory.tau_sensitivity``), which the filter then carries; on a wide
    area more references are scanned for it (:data:`TAU_SPREAD`). ``keep``: the layout's
    keep-outs as witnesses of the frame (:mod:`.keepout_frame`), where the references'
    model puts the obstacles far from them.
    """
    drift = ctx.drift
    if not drift.bootstraps:
        return
    t_start = yield Msg("clock")
    drift.full_scan_done(t_start)
    count = BOOTSTRAP_OBJECTS * (2 if _tau_spread(ctx) > TAU_SPREAD else 1)
    picks = bootstrap_picks.Picks(ctx.belief, ctx.landmarks, count)
    order = iter(picks)
    seen_objects, state, refuted = {}, {"used": 0, "t_last": t_start}, []

    def take(kind, rid, scanned, key=None):
        """Measure the model with a reference scanned again (:func:`_bootstrap_rows`),
        kept under ``key`` (by default ``(kind, id)``)."""
        _, t, seen = scanned
        _measure(drift, drift.scan, scanned, key or (kind, rid))
        if seen is not None:
            seen_objects[rid] = seen
        picks.found()
        state["used"] += 1
        state["t_last"] = t

    def scan_more(source=order, enough=None, widen=True):
        """Scan the picks in order until enough references measured the model."""
        for kind, rid, seen_t in source:
            searched: set = set()
            scanned = yield from _bootstrap_rows(ctx, kind, rid, seen_t, widen, searched)
            # what only a widened search found: confirmed by a second object, or refuted
            second = (yield from bootstrap_confirm.confirm(ctx, picks, rid, seen_t, scanned, _bootstrap_rows)
                      ) if scanned is not None and rid in searched else ()
            if scanned is not None and second is not None:
                take(kind, rid, scanned)
            elif scanned is not None:
                refuted.append((kind, rid, seen_t))
            if second:
                picks.take(second[0])
                take(*second[0][:2], second[1])
            if state["used"] >= (enough or (count if drift.velocity_known else 3 * BOOTSTRAP_OBJECTS)):
                return

    yield from scan_more()
    _jumped(drift.scan)
    # references the others contradict (a neighbour in a cluster taken for one: scale300
    # seed 1, 108 nm off in x, pulled the velocity 10 % off and every row's position up
    # to 24 nm) are left out, the fewest that leave the rest consistent, and others
    # scanned in their place
    aside = {}                          # left out: key -> (rows, times, sighting)
    for _ in range(BOOTSTRAP_OUTLIERS):
        out, back = left_out(drift.scan, {k: v[:2] for k, v in aside.items()}, BOOTSTRAP_GATE,
                             BOOTSTRAP_LEFT_TOGETHER, _jumped)
        if not out and not back:
            break
        for kind, rid in out:
            chi2 = drift.scan.disagreement((kind, rid))
            aside[(kind, rid)] = (*drift.scan.remove((kind, rid)), seen_objects.pop(rid, None))
            picks.left_out(rid)
            state["used"] -= 1
            yield Msg("event", (f"bootstrap: {rid} disagrees with the other references (χ² {chi2:.0f}): "
                                f"left out",), {"level": "warn"})
        for kind, rid in back:
            rows, times, seen = aside.pop((kind, rid))
            drift.scan.restore((kind, rid), rows, times)
            if seen is not None:
                seen_objects[rid] = seen
            picks.taken_back(rid)
            state["used"] += 1
            yield Msg("event", (f"bootstrap: {rid} agrees with the references scanned since: taken back",))
        _jumped(drift.scan)
        yield from scan_more()
        _jumped(drift.scan)
    if (yield from keepout_frame.witness(ctx, keep, _jumped)):
        for pick in refuted:    # what a widened search alone found, looked for again either side of the tear
            picks.put_back(pick)
    yield from tear_or_jump(ctx, picks.latest(), scan_more, take, _bootstrap_rows)
    told = jump_state(drift.scan)
    for kept, again, d in tear_doubles.doubles(ctx):
        if again in seen_objects and kept not in seen_objects:
            kept, again = again, kept
        ctx.belief.forget(again)
        ctx.refs.forget(again)
        picks.forget(again)
        seen_objects.pop(again, None)
        yield Msg("event", (f"bootstrap: {again} is {kept} imaged again by the tear of the full scan ({d:.1f} nm "
                            f"apart with the jump taken out): forgotten",))
    yield from narrow_tear(ctx, picks, take, _bootstrap_rows)
    # the tear's probes and the earliest rows' references lie before a tear and are
    # scanned last: a jump after the scan from the first of their times then fits as
    # well, and the first of equal fits (the scan's end, a reference's time, then the
    # tears) took it (allpushed, a tear at 150 s of 600, seeds 2, 5 and 10; mixed, 125 s
    # of 500, seed 2: objects put 300 nm off): told apart again where the jump moved
    told = yield from told_again(ctx, picks, scan_more, take, told, _bootstrap_rows)
    yield from _earliest_rows(ctx, picks, take)
    if (yield from told_again(ctx, picks, scan_more, take, told, _bootstrap_rows)) != told:   # a tear now?
        yield from narrow_tear(ctx, picks, take, _bootstrap_rows)
    used, t_last = state["used"], state["t_last"]
    if (said := jump_text(drift.scan)) is not None:
        yield Msg("event", (said,), {"level": "warn"})
    t_end = yield Msg("clock")
    ctx.ledger.purposes["bootstrap"] += t_end - t_start
    for oid, body, cov, t in seen_objects.values():   # by the scan's drift model, then the filter starts
        ctx.observe(oid, ctx.to_layout(body, t).at, t, cov)
    drift.restart(t_last)
    if not drift.velocity_known:
        yield Msg("event", (f"the drift velocity is not known in every direction: {used} reference(s) of the "
                            f"full scan did not measure it (the filter starts from its prior)",), {"level": "warn"})
        return
    v = drift.velocity()
    yield Msg("event", (f"drift from the full scan's skew: {v[0]:+.3f}, {v[1]:+.3f} nm/s "
                        f"(+/- {drift.velocity_std():.3f}) from {used} references",))
    ctx.log_drift(t_last)
    yield from emit_drift(ctx, t_last)


def _earliest_rows(ctx: RunContext, picks, take):
    """Where no reference lies on the full scan's first rows, the drift over them is the
    model's extrapolation, and with it where the layout's frame (the scanner's at the
    scan's start) now lies: references of rows 255-685 s of an 800 s scan left the
    drift's steady change at its prior and the estimate 13 nm off from the scan's end on
    (device seed 5). Once the model places every row closely, the unscanned particle,
    corner or rod (a rods-only scene's first rows hold nothing else: rodgap seed 10, no
    reference before 392 s of 1000) that would shrink the uncertainty of the drift since
    the start the most is scanned with short lines (no widened search), where its room
    allows them, while one shrinks that σ enough (:func:`~.bootstrap_picks.early_choice`),
    up to :data:`EARLY_REFERENCES`; one the others contradict is left out."""
    drift = ctx.drift
    scan, ep = drift.scan, drift.epoch
    rods = [("object", o.id, ctx.belief.seen[o.id].t) for o in ctx.belief.objects.values()
            if o.kind == "rod" and not o.edge]
    for _ in range(EARLY_REFERENCES):
        if not drift.velocity_known:
            return
        t = yield Msg("clock")
        now = t - ep
        if bootstrap_picks.early_sigma(scan, now) < bootstrap_picks.EARLY_FLOOR:
            return                              # before every candidate's room is measured
        cands = [p for s in picks.stretches for p in s] + rods
        room = bootstrap_picks.gaps(ctx.belief, ctx.landmarks, cands)
        best = bootstrap_picks.early_choice(scan, now, [(c, c[2] - ep, r) for c, r in zip(cands, room)],
                                            BOOTSTRAP_VAR)
        if best is None:
            return
        before, after, pick = best
        picks.take(pick)
        rods = [c for c in rods if c != pick]
        scanned = yield from _bootstrap_rows(ctx, *pick, widen=False)
        if scanned is None:
            continue
        trial = scan.trial()                    # against the others' model
        _measure(drift, trial, scanned, pick[:2])
        chi2 = trial.disagreement(pick[:2])
        if chi2 > gate_threshold(len(scanned[0]), BOOTSTRAP_GATE):
            yield Msg("event", (f"bootstrap: {pick[1]} disagrees with the other references (χ² {chi2:.0f}): "
                                f"left out",), {"level": "warn"})
            continue
        take(pick[0], pick[1], scanned)
        _jumped(scan)
        yield Msg("event", (f"bootstrap: {pick[1]}, on a row of {pick[2]:.0f} s, scanned again for the drift "
                            f"since the full scan began (σ {before:.1f} nm, expected {after:.1f})",))


def _measure(drift, scan, scanned, key) -> None:
    """Measure ``scan`` (the drift's scan model, or a trial copy) with a reference scanned
    again (:func:`_bootstrap_rows`), its components kept under ``key``."""
    rows, t, _ = scanned
    lam1 = drift.filter.creep.tau_sensitivity(t - drift.epoch)   # every move's, per unit λ
    for n, z, tau1, tau0, creep1, var in rows:
        scan.measure(n, z, tau1, tau0, BOOTSTRAP_VAR + var, creep1=creep1, lam1=lam1, key=key)


def _bootstrap_rows(ctx: RunContext, kind: str, rid: str, seen_t: float, widen: bool = True,
                    searched: set | None = None, shift=None):
    """Scan one bootstrap reference again: ``(rows, time, seen)`` with rows of ``(n, z,
    τ now, τ then, creep now, var)`` (``z``: the component along ``n`` of the drift
    between, the nominal creep taken out; creep now: the nominal creep of every move so
    far, and what the scan lines' compensation makes of the amplitude's error; var: the
    located position's variance along ``n``, the compensation's included), ``seen`` an
    object's sighting to record once the drift is known; None when it was not found, or
    is not yet known well enough along its edge to be scanned. ``searched`` gets ``rid``
    when only a widened search found it; ``shift``: an object looked for that far from its
    place (:mod:`.bootstrap_confirm`)."""
    drift = ctx.drift
    ep = drift.epoch
    if kind == "object":
        found = yield from locate(ctx, rid, widen=widen, resolve=shift is None, shift=shift)
        if found is None:
            return None
        body, cov, t, res = found
        if searched is not None and res.pattern == "lost_particle":
            searched.add(rid)
        # D(t) - D(τ) less the creep modelled now and then; the lines' compensation
        # erred by the creep amplitude's error times sens
        now = drift.creep_offset(t - ep)
        creep = now - drift.scan.creep_at(seen_t - ep)
        sens = res.creep_sensitivity()
        z = (np.asarray(body.at) - drift.origin - np.asarray(ctx.belief[rid].at) - creep
             + creep_terms.amplitude_error(drift)[0] * sens)
        now = now + sens
        rows = [(np.array(e), float(z @ e), t - ep, seen_t - ep, now, float(np.asarray(e) @ cov @ e))
                for e in ((1.0, 0.0), (0.0, 1.0))]
        return rows, t, (rid, body, cov, t)
    t_now = yield Msg("clock")
    if not ctx.landmarks.within_room(drift, rid, t_now):
        return None
    scanned = yield from scan_feature_lines(ctx, rid, agree=False)
    if scanned is None:
        return None
    res, placed, _, t = scanned
    feat = ctx.landmarks.features[rid]
    now = drift.creep_offset(t - ep)
    lc = res.line_creep if res.line_creep is not None else np.zeros((len(placed), 2))
    eps = creep_terms.amplitude_error(drift)[0]
    rows = [(n, float(n @ (p + o * n - drift.origin - np.asarray(site.point, float) - now
                           + drift.scan.creep_at(ts - ep) + eps * d)), t - ep, ts - ep, now + d,
             float(n @ ctx.scan_comp @ n) + step.std ** 2)
            for (p, n, _), o, site, ts, step, d in zip(placed, res.offsets, feat.sites, ctx.landmarks.seen[rid],
                                                       res.steps, lc)]
    return rows, t, None
