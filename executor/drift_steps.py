"""Drift measurements as plan stubs: a reference scanned before a push, a pushed object's
own scan folded in while it is still a reference, and the full scan's obstacles with
their rows' drift taken out (the drift velocity from the full scan's skew is
:mod:`~nanoasm.executor.drift_bootstrap`'s).

Free generator functions over a :class:`~nanoasm.executor.context.RunContext`; what to
measure and what a measurement means is the drift estimator's
(:mod:`nanoasm.executor.estimators`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import shapely

from .context import RunContext
from .engine import Msg
from .edge_scan import edge_pattern
from .landmarks import EDGE_SPACING
from .relocalise import keep_track
from .scan_steps import locate, run_pattern


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
