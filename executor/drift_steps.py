"""Drift measurements as plan stubs: a reference scanned before a push, a pushed object's
own scan folded in while it is still a reference, and the drift velocity from the full
scan's skew.

Free generator functions over a :class:`~nanoasm.executor.context.RunContext`; what to
measure and what a measurement means is the drift estimator's
(:mod:`nanoasm.executor.estimators`).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import shapely

from nanoasm.drift import gate_threshold

from . import creep_terms
from .context import RunContext
from .engine import Msg
from .edge_scan import edge_pattern
from .landmarks import EDGE_SPACING
from .relocalise import keep_track
from .scan_drift import JUMP_GATE
from .scan_steps import locate, run_pattern

#: Objects scanned again to find the drift velocity from the full scan's skew.
BOOTSTRAP_OBJECTS = 4
#: Twice as many where the creep time constant's prior uncertainty moves one side of the
#: area against the other by more than this (nm, 1σ: ``c σ_λ side / ln 10``, twice a
#: located centre's own): its error offsets a reference in proportion to where it lies,
#: which four references along the rows take for velocity (wide, 16 µm, seeds 1-10: λ at
#: the run's end 0.10 from the truth with four, 0.06 with eight, medians); on a 4 µm area
#: it is 3.5 nm, on 5 µm 4.3.
TAU_SPREAD = 4.0
#: Bootstrap references left out at most, each because the others contradict it beyond
#: :data:`BOOTSTRAP_GATE` (and each replaced by the next pick).
BOOTSTRAP_OUTLIERS = 3
#: Gate probability of that test (χ² of a reference against the others' model).
BOOTSTRAP_GATE = 0.9999
#: Variance (nm²) of a component a bootstrap reference measures: the located centre's
#: and the full scan's (2 nm each), and what the model leaves (the random walk, creep).
BOOTSTRAP_VAR = 16.0


def emit_drift(ctx: RunContext, t: float):
    """Emit the drift estimate (for the estimators that have one to tell)."""
    if ctx.drift.emits:
        yield Msg("emit", ("drift", ctx.drift.doc(t)))


def fold(ctx: RunContext, obj_id: str, scanner_at, cov, t: float, *, reference: bool = False,
         scan=None) -> bool:
    """Fold a measured position (scanner frame) of ``obj_id`` into the drift estimate, if
    it measures drift (``reference``: the reference the estimator chose; ``scan``: the
    local scan that located it, whose lines' creep compensation the estimate models);
    False only when the estimate's gate rejected it (it moved on its own)."""
    measure = ctx.drift.measure_reference if reference else ctx.drift.measure
    sens = None if scan is None else scan.creep_sensitivity()
    folded = measure(obj_id, scanner_at, cov, t, ctx.refs, ctx.ledger.pushed, ctx.belief.lost, sens)
    if folded is not None:
        ctx.log_drift(t)
    return folded is not False


def take_reference(ctx: RunContext, near, obj_id: str | None = None, *, force: bool = False):
    """Measure drift on the reference the estimator wants before a push of ``obj_id``
    near ``near`` (an untouched object, a fixed feature, the anchor, or none); with
    ``force``, even if none is due."""
    t = yield Msg("clock")
    here = yield Msg("position")
    ctx.here = ctx.config.codes_to_nm(np.asarray(here))[:2]
    choice = ctx.drift.reference_target(ctx, t, near, obj_id, force=force)
    if choice is None:
        return
    if choice.kind == "feature":
        yield from scan_feature(ctx, choice.id)
    else:
        yield from scan_object_reference(ctx, choice.id)
    t_end = yield Msg("clock")
    ctx.ledger.purposes["reference"] += t_end - t


def suspect_drift(ctx: RunContext, label: str, near, *, count: bool = True):
    """``label`` was not where the estimate put it: perhaps it moved, perhaps the drift
    jumped. It counts as a rejected reference, and a reference is measured at once: out
    of place too, the estimate is relocalised. Returns whether it was.

    Not ``count``: a push lost its object, which says nothing of where the drift put it
    (slips are common at scale), so references alone decide: one at once, and while each
    is rejected another, up to the streak that relocalises. A drift jump under the tip
    rejects them all; a reference the slipped object shoved is one, and the next ends
    the streak."""
    if not ctx.drift.uses_landmarks:
        return False
    t = yield Msg("clock")
    if count:
        ctx.drift.reject(label, t)
    for _ in range(1 if count else ctx.options.relocalise_rejections):
        before = ctx.drift.trust.rejections
        yield from take_reference(ctx, near, label, force=True)
        if ctx.drift.trust.rejections <= before:      # agreed (the streak ended), or none left
            break
    return (yield from keep_track(ctx))


def scan_object_reference(ctx: RunContext, ref: str):
    """Locate an object as a drift reference and fold it in."""
    found = yield from locate(ctx, ref)
    if found is None:
        if ctx.drift.references_are_objects:
            ctx.belief.lose(ref)
            ctx.drift.reject(ref, (yield Msg("clock")))
        return
    body, cov, t, res = found
    if not fold(ctx, ref, body.at, cov, t, reference=True, scan=res):
        yield Msg("event", (f"{ref} moved on its own (gated out of the drift estimate; "
                            f"{ctx.refs.note(ref)})",), {"level": "warn"})
    yield from emit_drift(ctx, t)
    if ctx.drift.references_are_objects:
        ctx.observe(ref, ctx.to_layout(body, t).at, t, cov)


def scan_feature_lines(ctx: RunContext, fid: str, *, agree: bool = True):
    """Scan the sites of fixed feature ``fid`` where the estimate puts them; returns
    ``(result, placed sites (scanner point, normal, height), offset used, time)`` or
    None when the feature was not found (a miss: counted, and told). ``agree``: two
    sites of one edge must agree (not while the velocity that takes the full scan's
    rows apart is still unknown: the bootstrap's)."""
    marks, est = ctx.landmarks, ctx.drift
    t = yield Msg("clock")
    off = est.offset(t)
    reach = marks.reach(est, fid, t)
    placed = [(p + off, n, h) for p, n, h, _ in marks.sites(est, fid)]
    res = yield from run_pattern(ctx, edge_pattern(placed, reach, spacing=EDGE_SPACING,
                                                   site_stds=marks.check_stds(est, fid), agree=agree))
    if not res.found:
        retired = marks.missed(fid)
        yield Msg("event", (f"feature {fid} not found within {reach:.0f} nm ({res.reason})"
                            + ("; retired" if retired else ""),), {"level": "warn"})
        return None
    return res, placed, off, (ctx.scan_ref if ctx.scan_ref is not None else t)


def scan_feature(ctx: RunContext, fid: str):
    """Scan a fixed feature and fold the offset components it measures (each site's
    crossing, scanner frame, less where the full scan saw it); a feature not found, or
    found out of place, is a miss and a rejection. Returns whether it was folded in."""
    marks, est = ctx.landmarks, ctx.drift
    scanned = yield from scan_feature_lines(ctx, fid)
    if scanned is None:
        est.reject(fid, (yield Msg("clock")))
        return False
    res, placed, off, t_scan = scanned
    H = np.array([n for _, n, _ in placed])
    taus = marks.taus(est, fid)
    # each crossing (scanner frame) less where the full scan saw it, that row's creep out
    z = np.array([n @ (p + o * n - est.origin - np.asarray(site.point, float) + est.scan.creep_at(tau))
                  for (p, n, _), o, site, tau in zip(placed, res.offsets, marks.features[fid].sites, taus)])
    line_stds = [step.std for step in res.steps]
    R = marks.measurement_cov(est, fid, line_stds) + H @ ctx.scan_comp @ H.T
    ok = est.measure_feature(fid, z, H, R, t_scan, taus, _site_creep(res, H))
    if ok:
        marks.found(fid)
    else:
        retired = marks.missed(fid)
        yield Msg("event", (f"feature {fid} out of place by {np.abs(res.offsets).max():.0f} nm "
                            f"(gated out of the drift estimate)" + ("; retired" if retired else ""),),
                  {"level": "warn"})
    ctx.log_drift(t_scan)
    yield from emit_drift(ctx, t_scan)
    return ok


def _site_creep(res, normals) -> np.ndarray | None:
    """Each edge site's offset per unit relative error of the creep amplitude its line
    was compensated with (its line's creep along its normal), or None."""
    if res.line_creep is None or len(res.line_creep) != len(normals):
        return None
    return np.einsum("ij,ij->i", np.asarray(normals, float), res.line_creep)


def _bootstrap_picks(ctx: RunContext, count: int) -> list[tuple[str, str, float]]:
    """What the bootstrap may scan again, in order: ``(kind, id, time seen)``. First
    ``count`` spread over the full scan's rows, latest first (their
    drift since is the smallest, so their lines are short, and every one sharpens the
    velocity that sizes the next one's lines), then the rest, latest first, for when
    those do not measure both coordinates. Particles and corners measure both; straight
    edges follow them."""
    belief, marks = ctx.belief, ctx.landmarks
    both = [("object", o.id, belief.seen[o.id].t) for o in belief.objects.values()
            if o.kind == "particle" and not o.edge]
    feats = [("feature", fid, float(np.mean(marks.seen[fid]))) for fid in marks.features]
    both += [c for c in feats if marks.features[c[1]].kind == "corner"]
    edges = [c for c in feats if c not in both]
    both.sort(key=lambda c: (c[2], c[1]))
    if not both:
        return sorted(edges, key=lambda c: (-c[2], c[1]))
    k = min(count, len(both))
    spread = [both[round(j * (len(both) - 1) / max(k - 1, 1))] for j in range(k)]
    first = sorted(dict.fromkeys(spread), key=lambda c: (-c[2], c[1]))
    rest = sorted((c for c in both + edges if c not in first), key=lambda c: (-c[2], c[1]))
    return first + rest


def _tau_spread(ctx: RunContext) -> float:
    """How far (nm, 1σ) the creep time constant's prior uncertainty moves one side of the
    area against the other: ``c σ_λ side / ln 10``."""
    creep = ctx.drift.params.creep
    return creep.amplitude * creep.tau_std * max(ctx.belief.area) / math.log(10.0)


def unskewed_obstacles(obstacles, drift, row_time) -> tuple:
    """The full scan's obstacles with each vertex's row drift taken out, as
    :meth:`RunContext.position` does for objects seen only in the full scan (``row_time(y)``:
    when the row at ``y`` was scanned). Computed once the drift is bootstrapped: over a
    frame of minutes the rows drift apart by hundreds of nm, which sheared and shifted the
    electrodes the planner keeps rods and particles clear of."""
    out = []
    for ob in obstacles:
        poly = [tuple(float(v) for v in drift.unskew(np.asarray(p, float), row_time(p[1]) - drift.epoch))
                for p in ob.polygon]
        out.append(replace(ob, polygon=_valid_ring(poly)))
    return tuple(out)


def _valid_ring(poly: list) -> tuple:
    """``poly``'s vertices, or where moving them by their rows' drift made the ring cross
    itself (a jump that tore the full scan, placed between two references' rows, moves the
    rows between by the jump or not, as they may not have been), the convex hull of them:
    a keep-out that covers the obstacle however its rows lie (the planner's union of
    keep-outs failed on the crossed ring: mixed seed 1, 300 nm at 250 s)."""
    shape = shapely.Polygon(poly)
    if len(poly) < 3 or shape.is_valid:
        return tuple(poly)
    hull = shapely.MultiPoint(poly).convex_hull
    if not isinstance(hull, shapely.Polygon):
        return tuple(poly)
    return tuple((float(x), float(y)) for x, y in hull.exterior.coords[:-1])


def bootstrap(ctx: RunContext):
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
    area more references are scanned for it (:data:`TAU_SPREAD`).
    """
    drift = ctx.drift
    if not drift.bootstraps:
        return
    t_start = yield Msg("clock")
    drift.full_scan_done(t_start)
    count = BOOTSTRAP_OBJECTS * (2 if _tau_spread(ctx) > TAU_SPREAD else 1)
    picks = iter(_bootstrap_picks(ctx, count))
    seen_objects, state = {}, {"used": 0, "t_last": t_start}

    def scan_more():
        """Scan the picks in order until enough references measured the model."""
        for kind, rid, seen_t in picks:
            scanned = yield from _bootstrap_rows(ctx, kind, rid, seen_t)
            if scanned is not None:
                rows, t, seen = scanned
                lam1 = drift.filter.creep.tau_sensitivity(t - drift.epoch)   # every move's, per unit λ
                for n, z, tau1, tau0, creep1, var in rows:
                    drift.scan.measure(n, z, tau1, tau0, BOOTSTRAP_VAR + var, creep1=creep1, lam1=lam1,
                                       key=(kind, rid))
                if seen is not None:
                    seen_objects[rid] = seen
                state["used"] += 1
                state["t_last"] = t
            if state["used"] >= (count if drift.velocity_known else 3 * BOOTSTRAP_OBJECTS):
                return

    yield from scan_more()
    _jumped(drift)
    # a reference the others contradict (a neighbour in a cluster taken for it: scale300
    # seed 1, 108 nm off in x, pulled the velocity 10 % off and every row's position up
    # to 24 nm) is left out, and another scanned in its place
    for _ in range(BOOTSTRAP_OUTLIERS):
        worst = drift.scan.worst()
        if worst is None or worst[1] <= gate_threshold(worst[2], BOOTSTRAP_GATE):
            break
        (kind, rid), chi2, _ = worst
        drift.scan.remove((kind, rid))
        seen_objects.pop(rid, None)
        state["used"] -= 1
        yield Msg("event", (f"bootstrap: {rid} disagrees with the other references (χ² {chi2:.0f}): "
                            f"left out",), {"level": "warn"})
        yield from scan_more()
        _jumped(drift)
    used, t_last = state["used"], state["t_last"]
    yield from _jump_event(drift)
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


def _jumped(drift) -> None:
    """Take a jump of the drift since the full scan began (while it was made, before the
    references are scanned again, or while they are) into the model once they make it
    evident (:data:`JUMP_GATE`); once in, place it again as references are left out or
    added, and out again where it no longer passes the gate (mixed seed 3, a tear at 250 s
    below every reference's row: the first references made a jump of 120 nm evident, the
    ones scanned after them did not). Without it a jump is taken for velocity: 300 nm just
    after a 500 s scan read as 1.1 nm/s, and relocalisations after it moved the estimate by
    90-260 nm again and again (mixed seed 1; seeds 1-3 filled no slot)."""
    scan = drift.scan
    _, _, stat, since = scan.jump_evidence()
    if stat > JUMP_GATE:
        scan.take_jump(since)
    elif scan.stepped:
        scan.drop_jump()


def _jump_event(drift):
    """Say what jump the bootstrap took into the model, if any."""
    scan = drift.scan
    if not scan.stepped:
        return
    jump, since = scan.jump, scan.tau_jump
    std = math.sqrt(max(float(np.linalg.eigvalsh(scan.cov_j[-2:, -2:])[-1]), 0.0))
    when = (f"during the full scan, about its row of {since + scan.epoch:.0f} s" if since < scan.tau_end
            else f"after the full scan, before {since + scan.epoch:.0f} s")
    yield Msg("event", (f"the drift jumped by {jump[0]:+.0f}, {jump[1]:+.0f} nm (± {std:.1f}) {when}: taken into "
                        f"the model",), {"level": "warn"})


def _bootstrap_rows(ctx: RunContext, kind: str, rid: str, seen_t: float):
    """Scan one bootstrap reference again: ``(rows, time, seen)`` with rows of ``(n, z,
    τ now, τ then, creep now, var)`` (``z``: the component along ``n`` of the drift
    between, the nominal creep taken out; creep now: the nominal creep of every move so
    far, and what the scan lines' compensation makes of the amplitude's error; var: the
    located position's variance along ``n``, the compensation's included), ``seen`` an object's sighting to record once the drift is
    known; None when it was not found, or is not yet known well enough along its edge to
    be scanned."""
    drift = ctx.drift
    ep = drift.epoch
    if kind == "object":
        found = yield from locate(ctx, rid)
        if found is None:
            return None
        body, cov, t, res = found
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
