"""Relocalisation as a plan stub: when the drift estimate can no longer be trusted, scan a
distinctive window of the sample again and register it to the first full scan.

The first full scan (layout frame) shows what lay in each window when its rows were
scanned; a new scan of the window, placed where the estimate puts it, shows the same
content shifted by the estimate's error. Phase correlation
(:func:`~nanoasm.executor.registration.register`) measures that shift with sub-pixel
precision. Both scans run row by row at one line rate, so the drift during each shears
them alike and the shift compares their first rows: the scanner offset of the layout
origin when the window's first row was scanned is the estimate then, plus the shift,
plus the drift the full scan carried at the reference's first row (the velocity and
creep that take a full-scan position out of its row's drift). The filter then starts
its offset afresh from that measurement (:meth:`~nanoasm.drift.DriftFilter.reinitialise`).

Objects that moved since the full scan would spoil the match: pixels near where they
were (in the full scan) and near where they are believed now (in the new scan) are
masked out of the registration.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from scipy import ndimage

from . import creep_terms
from .context import RunContext
from .engine import Msg
from .jump_recheck import recheck
from .registration import register
from .scan_images import scan_window

#: Pixels within this distance (nm) beyond an object's footprint are masked when it moved.
MASK_MARGIN = 40.0
#: The widening of a moved object's mask for its uncertainty is at most this, nm.
MAX_MASK = 300.0


def keep_track(ctx: RunContext):
    """Relocalise if the estimator says it must (see :meth:`needs_relocalisation`);
    returns whether it did. An estimate merely grown uncertain is relocalised only when
    a registration would make it at least twice as good: what a registration measures
    is relative to the full scan, so the velocity that took the full scan's rows apart
    bounds it."""
    t = yield Msg("clock")
    why = ctx.drift.needs_relocalisation(t, ctx.options)
    if why is None:
        return False
    kind, text = why
    if kind == "sigma" and not 2.0 * achievable(ctx) < ctx.drift.sigma(t):
        return False
    return (yield from relocalise(ctx, text))


def achievable(ctx: RunContext) -> float:
    """The σ (nm) a registration of the best window would leave: its own precision
    (about a pixel's tenth) and the full scan's row drift at the window."""
    marks, image = ctx.landmarks, ctx.full_scan
    if image is None or not marks.windows or marks.rows is None:
        return math.inf
    x0, y0, x1, y1 = marks.windows[0].region
    tau = marks.rows[0] + ((0.5 * (y0 + y1) - image.origin[1]) / image.pixel_size) * marks.rows[1] - ctx.drift.epoch
    return math.sqrt((0.1 * image.pixel_size) ** 2 + 1.0 + float(np.linalg.eigvalsh(ctx.drift.skew_cov(tau))[-1]))


def _disturbed(ctx: RunContext) -> list[str]:
    """Objects that are no longer where the full scan saw them, or may not be."""
    refs, belief = ctx.refs, ctx.belief
    moved = set(ctx.ledger.pushed) | belief.touched | belief.lost | refs.gated | set(refs.quarantine)
    return sorted(oid for oid in moved if oid in belief.objects)


def _mask(image, bodies) -> np.ndarray:
    """True where ``image`` (a HeightImage) is not near any of ``bodies`` ((Body, extra
    nm): the footprint widened by ``extra`` and :data:`MASK_MARGIN`). Each body is
    measured over the pixels of its widened bounding box only (those beyond it are
    farther than the widening), so a full scan's mask costs its pixels once plus the
    bodies' boxes, not its pixels per body (1000 objects on a 4000-pixel scan: N^2)."""
    x, y = image.pixel_centres()
    keep = np.ones(image.shape, bool)
    for body, extra in bodies:
        r = body.radius + extra + MASK_MARGIN
        (ax, ay), (bx, by) = body.core()
        i0, i1 = np.searchsorted(y, min(ay, by) - r), np.searchsorted(y, max(ay, by) + r, side="right")
        j0, j1 = np.searchsorted(x, min(ax, bx) - r), np.searchsorted(x, max(ax, bx) + r, side="right")
        if i0 >= i1 or j0 >= j1:
            continue
        px, py = x[None, j0:j1], y[i0:i1, None]
        d = np.array([bx - ax, by - ay])
        u = np.clip(((px - ax) * d[0] + (py - ay) * d[1]) / max(d @ d, 1e-12), 0.0, 1.0)
        dist = np.hypot(px - ax - u * d[0], py - ay - u * d[1])
        keep[i0:i1, j0:j1] &= dist > r
    return keep


def relocalise(ctx: RunContext, why: str):
    """Scan the best relocalisation windows until one registers; restart the offset from
    it. Returns whether the estimate was relocalised (False: no window registered; the
    run goes on with the estimate it had, its references re-admitted)."""
    est, marks, image = ctx.drift, ctx.landmarks, ctx.full_scan
    t_start = yield Msg("clock")
    yield Msg("event", (f"relocalising the drift estimate: {why}",), {"level": "warn"})
    if image is None or not marks.windows or marks.rows is None:
        yield Msg("event", ("cannot relocalise: " + ("no full scan kept" if image is None
                                                       else "no distinctive window in the full scan"),),
                  {"level": "error"})
        est.relocalise_failed(t_start)
        return False
    cfg = ctx.config
    lo, hi = cfg.lower[:2], cfg.upper[:2]
    moved = _disturbed(ctx)
    first = {o.id: o for o in ctx.env_objects} if ctx.env_objects else {}
    then = [(first[o], 0.0) for o in moved if o in first]
    now = [(ctx.belief[o], min(est.radius(t_start, ctx.belief.seen.get(o), None, ctx.options), MAX_MASK))
           for o in moved if o not in ctx.belief.lost]
    t_full0, line_time = marks.rows
    here = ctx.here if ctx.here is not None else est.offset(t_start) + 0.5 * np.asarray(image.extent)
    near = sorted(marks.windows, key=lambda w: math.dist(here, _centre(w) + est.offset(t_start)))
    for k, w in enumerate(near):
        t = yield Msg("clock")
        off = est.offset(t)
        x0, y0, x1, y1 = w.region
        region = (x0 + off[0], y0 + off[1], x1 + off[0], y1 + off[1])
        if region[0] < lo[0] or region[1] < lo[1] or region[2] > hi[0] or region[3] > hi[1]:
            continue
        pixels = max(16, int(round((x1 - x0) / image.pixel_size)))
        scan, t_end = yield from scan_window(ctx, pixels, region, f"relocalisation window {k + 1}")
        window = replace(scan, origin=(scan.origin[0] - off[0], scan.origin[1] - off[1]))
        window, inside = _unsheared(window, est, (t, t_end), (t_full0, line_time, (y0 - image.origin[1]) / image.pixel_size))
        reg = register(image, window, reference_mask=_mask(image, then), moving_mask=_mask(window, now) & inside)
        if not reg.ok:
            yield Msg("event", (f"window {k + 1} did not register ({reg.reason})",), {"level": "warn"})
            continue
        t_mid, tau, z, creep_cov = _window_offset(est, off, reg.shift, (t, t_end, pixels),
                                       (t_full0, line_time, (y0 - image.origin[1]) / image.pixel_size,
                                        (y1 - y0) / image.pixel_size))
        R = np.eye(2) * (reg.std ** 2 + 1.0) + creep_cov
        old, since, confirmed = est.offset(t_mid), est.trust.streak_start, est.trust.confirmed_at
        forgiven = est.relocalised(t_mid, z, R, tau, ctx.refs)
        new, cov = est.offset(t_mid), est.offset_cov(t_mid)
        marks.forgive(forgiven)
        ctx.belief.lost.difference_update(forgiven)      # references missed for the drift's jump
        _correct_beliefs(ctx, new - old, since)
        ctx.ledger.purposes["relocalise"] += t_end - t_start
        ctx.log_drift(t_mid)
        shift = np.asarray(new - old)
        yield Msg("event", (f"relocalised by window {k + 1} at ({0.5 * (x0 + x1):.0f}, {0.5 * (y0 + y1):.0f}) "
                            f"(match {reg.score:.2f}): the estimate moved {shift[0]:+.0f}, {shift[1]:+.0f} nm "
                            f"(± {math.sqrt(cov[0, 0]):.1f})",))
        if est.emits:
            yield Msg("emit", ("drift", est.doc(t_mid)))
        yield from recheck(ctx, confirmed, since, shift)
        return True
    t_end = yield Msg("clock")
    ctx.ledger.purposes["relocalise"] += t_end - t_start
    est.relocalise_failed(t_end)
    yield Msg("event", ("relocalisation failed: no window registered; going on with the estimate as it was",),
              {"level": "error"})
    return False


def _window_offset(est, off, shift, new_rows, old_rows) -> tuple[float, float, np.ndarray, np.ndarray]:
    """What a registered window measures: ``(t, τ, z, cov)`` with ``z`` (nm) the drift since
    the epoch at ``t``, the middle of the new scan, less the full scan's at ``τ``, the
    middle of the window's rows in it (creep then taken out).

    The registration's shift is the content-weighted mean over rows of what each row of
    the new scan (placed with the estimate ``off``) is displaced by against the same
    row of the full scan: it compares the scans' middles, where a drift linear over the
    rows (a velocity, alike or not in the two) equals its mean. Creep is not linear: the
    moves made just before the new scan still creep fast through its first rows (tens
    of nm over a 200-row window), so the mean of the modelled creep over the rows, less
    its value at the middle, is taken out too. ``new_rows``: ``(start, end, rows)`` of
    the new scan, instrument s; ``old_rows``: ``(first line's start, line time, first
    row, rows)`` of the window in the full scan; ``cov`` (nm²): what the creep taken out
    may err by, at the amplitude's uncertainty."""
    t0, t1, n = new_rows
    t_full0, line_time, row0, rows = old_rows
    s = t0 + (np.arange(n) + 0.5) * (t1 - t0) / n - est.epoch
    t_mid = t0 + 0.5 * (t1 - t0)
    taus = t_full0 + (row0 + np.arange(max(int(round(rows)), 1)) + 0.5) * line_time - est.epoch
    tau = t_full0 + (row0 + 0.5 * rows) * line_time - est.epoch
    creep_now = np.mean([est.creep_offset(v) for v in s], axis=0) - est.creep_offset(t_mid - est.epoch)
    creep_then = np.mean([est.scan.creep_at(v) for v in taus], axis=0)
    z = off - est.origin + np.asarray(shift, float) + creep_then - est.creep_scale() * creep_now
    return t_mid, float(tau), z, creep_terms.amplitude_error(est)[1] * np.outer(creep_now, creep_now)


def _unsheared(window, est, new_rows, old_rows):
    """The new scan with its rows moved to where they would lie had it drifted against
    the full scan evenly: row ``i`` by how much more (or less) the estimate says its
    content drifted, between the full scan's row and this one, than the rows' mean did;
    and True where the pixels so taken lie inside the scan. Creep right after the travel
    to the window shears a 200-row scan by up to 130 nm more than the full scan's same
    rows (measured on scale300): the registration then measures the shift of the rows
    the content sits in, 10-30 nm from the mean that :func:`_window_offset` takes it
    for; unsheared, it measures that mean. ``new_rows``: ``(start, end)`` of the new
    scan, instrument s; ``old_rows``: ``(first line's start, line time, first row)`` of
    the window in the full scan."""
    t0, t1 = new_rows
    t_full0, line_time, row0 = old_rows
    rows, cols = window.shape
    s = t0 + (np.arange(rows) + 0.5) * (t1 - t0) / rows
    taus = t_full0 + (row0 + np.arange(rows) + 0.5) * line_time - est.epoch
    now = np.array([est.offset(v) for v in s])
    then = np.array([-est.unskew(np.zeros(2), tau) for tau in taus])      # the full scan's row drift
    dev = (now - then) - (now - then).mean(axis=0)
    i, j = np.mgrid[0:rows, 0:cols].astype(float)
    ci, cj = i + dev[:, 1, None] / window.pixel_size, j + dev[:, 0, None] / window.pixel_size
    inside = (ci >= 0.0) & (ci <= rows - 1.0) & (cj >= 0.0) & (cj <= cols - 1.0)
    height = ndimage.map_coordinates(np.asarray(window.height, float), [ci, cj], order=3, mode="nearest")
    return replace(window, height=height), inside


def _centre(w) -> np.ndarray:
    x0, y0, x1, y1 = w.region
    return np.array([0.5 * (x0 + x1), 0.5 * (y0 + y1)])


def _correct_beliefs(ctx: RunContext, shift: np.ndarray, since: float | None) -> None:
    """Objects seen since the estimate went wrong (``since``: the first rejection of the
    streak) were put into the layout frame with it: move them by what the relocalisation
    corrected (``shift``: new less old offset)."""
    if since is None or math.hypot(*shift) < 1e-9:
        return
    for oid, seen in ctx.belief.seen.items():
        if seen.t >= since and oid not in ctx.belief.lost:
            ctx.belief.reframe(oid, shift)
            ctx.corrected = True

