"""Local scan patterns for rods before and after a push (seed 5.3, Fig. 5.2).

Generators as in :mod:`nanoasm.executor.local_scan`: they yield
:class:`~nanoasm.executor.scan_lines.ScanLine` requests, are sent the profiles and
return a :class:`~nanoasm.executor.scan_lines.LocalScanResult` with centre, angle and
length.

Every edge crossing lies on the rod's outline at the edge level (a capsule around the
rod's core, :func:`~nanoasm.executor.capsule_fit.fit_capsule`), so the pose comes from a
least-squares fit of that outline to all the crossings of the pattern. For lines at
right angles to the rod this is the seed's midpoint rule; for the oblique lines after a
push it is not misled by a line through a rounded end; and it measures the tip's
broadening from the cross chords, so the length needs no tip model. A fit whose length
disagrees with the believed length (the lines did not cross the rod as assumed, e.g.
the rod ended up nearly along the push) is refused, and the pattern falls back once to
cross lines at right angles to the best axis seen so far.
"""

from __future__ import annotations

import math
from collections.abc import Generator

import numpy as np

from nanoasm.param import number

from .capsule_fit import fit_capsule, near_angle
from .scan_lines import (AXIS_PEAK, DEFAULT_OPTIONS, LineOutcome, LocalScanResult, ScanLine,
                         ScanOptions, axis, make_line, measure_line, missed, perp, point, step_offsets,
                         unit, wedge)

Pattern = Generator[ScanLine, np.ndarray, LocalScanResult]

#: A fit less certain of the angle than this (degrees, 1-sigma) is refused.
MAX_ANGLE_STD = 10.0
#: A rod seen at one end only is placed by cross lines whose summits are all within
#: this share of its believed diameter (identification measures it to about 1 %).
ONE_END_HEIGHT = 0.1


def is_rod(out: LineOutcome, d: float, opts: ScanOptions) -> bool:
    """Whether a cross line's found bump is of the rod's height: at most
    ``opts.rod_height`` above ``d`` (plus three noise). A particle crossed beside the rod
    would tilt the axis through the two lines: in the bundled rods example (seed 1) an 81 nm
    summit beside a 74.6 nm rod put the rod 85 nm along its axis from where it lay. A grazed
    end, lower, is left to the caller."""
    if opts.rod_height is None or out.edges.peak is None:
        return True
    return out.edges.peak <= (1 + opts.rod_height) * d + 3 * out.edges.noise


def rod_args(centre, angle, length, diameter, r_max, names=("centre", "angle")):
    c = point(names[0], centre)
    th = number(names[1], angle)
    d = number("diameter", diameter, positive=True)
    L = number("length", length, positive=True)
    if L < d:
        raise ValueError(f"length must be at least the diameter ({d:g}), got {L:g}")
    return c, th, L, d, number("r_max", r_max, nonnegative=True)


def rod_before(centre, angle: float, length: float, diameter: float, r_max: float, *,
               measure_angle: bool = False, options: ScanOptions = DEFAULT_OPTIONS) -> Pattern:
    """Find a rod's centre and length before a push (seed 5.3, Fig. 5.2 left).

    Line L0 crosses the rod at right angles through its believed centre; while it finds
    nothing it is moved alternately along the rod by L/4 until found or the lines cover
    ``r_max``. Line V along the rod through the midpoint of P1, P2 gives the ends Q1, Q2.
    Cross lines reach ``d + r_max + margin`` to both sides of the axis (the seed's
    ``l > d + r_max`` read as the reach either side, as in :func:`line_length`); V spans
    every place the rod can be: it contains P's midpoint and its centre is within
    ``r_max`` of the believed one (length ``L + 2 r_max + 2 margin`` at most).

    The seed takes the orientation as known (drift translates); the angle is then the
    believed one (``angle_std`` None). ``measure_angle`` adds one more cross line, half
    the rod's straight part (at least L/4) along it toward the believed centre (or the
    other way if that misses), and V runs through both midpoints, as after a push.

    Parameters
    ----------
    centre : (2,) array-like
        Believed centre (nm).
    angle : float
        Believed axis angle (degrees).
    length, diameter : float
        Rod length L (ends included) and diameter d (nm).
    r_max : float
        Largest expected error of ``centre`` (nm).
    measure_angle : bool
    options : ScanOptions
    """
    c, th, L, d, r_max = rod_args(centre, angle, length, diameter, r_max)
    return _rod_before(c, th, L, d, r_max, bool(measure_angle), options.resolved(d))


def _cross_line(centre, a_hat, off, reach, opts, role):
    return make_line(centre + off * a_hat, perp(a_hat), -reach, reach, opts.spacing, role)


def _rod_before(c, th, L, d, r_max, measure_angle, opts, pattern="rod_before", lines=None,
                fallback=True):
    lines = [] if lines is None else lines
    a_hat = axis(th)
    reach = d + r_max + opts.margin
    hit = None
    for off in step_offsets(L / 4, r_max):
        if len(lines) >= opts.max_lines:
            return missed(pattern, f"line budget of {opts.max_lines} used up", lines)
        out = yield from measure_line(_cross_line(c, a_hat, off, reach, opts, f"L{len(lines)}"),
                                      reach, opts)
        lines.append(out)
        if out.edges.found and is_rod(out, d, opts):
            hit = off, out
            break
    if hit is None:
        return missed(pattern, f"nothing within r_max = {r_max:g} nm ({len(lines)} lines)", lines)
    off, out = hit
    cross = [out]
    if measure_angle:                           # a second line as far along as the core allows
        side = -1.0 if off > 0 else 1.0
        sep = max(L / 4, (L - d) / 2)
        for off2 in (off + side * sep, off - side * sep):
            if len(lines) >= opts.max_lines:
                break
            line = _cross_line(c, a_hat, off2, reach, opts, f"L{len(lines)}")
            out2 = yield from measure_line(line, reach, opts)
            lines.append(out2)
            if out2.edges.found and is_rod(out2, d, opts):
                cross.append(out2)
                break
        if len(cross) < 2:
            return missed(pattern, "no second cross line found the rod to measure its angle",
                          lines)
    w = axis_through(cross, a_hat) if measure_angle else a_hat
    result = yield from finish_rod(pattern, cross, w, c, th, L, d, r_max, opts,
                                    not measure_angle, lines, "")
    if result.found or not fallback:
        return result
    return (yield from _fallback(pattern, lines, th, L, d, opts))


def rod_after(start, start_angle: float, length: float, diameter: float, push_point,
              push_direction, push_length: float, r_max: float, *, predicted=None,
              predicted_angle: float | None = None, min_alpha: float = 15.0,
              options: ScanOptions = DEFAULT_OPTIONS) -> Pattern:
    """Find a rod's pose after a push (seed 5.3, Fig. 5.2 right).

    Line L'0 runs through the push point T along the push; if it misses, the next runs
    along O_aO' (through the start centre, parallel); then the line is moved alternately
    up and down by (L/4) sin α (α between the push and the rod's start orientation)
    until two lines have crossed the rod, or the lines are farther than ``L + r_max``
    from T (no point of the rod can be). Line V' through the two crossing midpoints
    gives the ends Q'1, Q'2. If V' passes an end off-axis by more than half the rod's
    width, one more line along the fitted axis is scanned and fitted in.

    L'0 runs from ``d + r_max + margin`` behind T to as far beyond T + Δ u: length
    ``Δ + 2(d + r_max + margin)``, the seed's ``l' > Δ + 2(d + r_max)``. The other
    lines span the same reach around where the start and the predicted rod cross them.

    When α is below ``min_alpha`` the lines would run nearly along the rod and their
    midpoints would not fix its axis; the pattern then runs :func:`rod_before` with
    ``measure_angle`` around the predicted pose instead.

    Parameters
    ----------
    start : (2,) array-like
        Rod centre O_a before the push (nm).
    start_angle : float
        Rod angle before the push (degrees).
    length, diameter : float
    push_point : (2,) array-like
        T, where the tip met the rod (nm).
    push_direction : (2,) array-like
    push_length : float
        Δ, the tip's travel while pushing (nm).
    r_max : float
        Largest expected error of the predicted pose (nm).
    predicted : (2,) array-like, optional
        Centre predicted by the push model (O'); ``start + Δ u`` when not given.
    predicted_angle : float, optional
        Angle predicted by the push model; ``start_angle`` when not given.
    min_alpha : float
        Smallest α (degrees) for the seed's pattern.
    options : ScanOptions
    """
    c0, th0, L, d, r_max = rod_args(start, start_angle, length, diameter, r_max,
                                     ("start", "start_angle"))
    t = point("push_point", push_point)
    u = unit("push_direction", push_direction)
    delta = number("push_length", push_length, nonnegative=True)
    c1 = c0 + delta * u if predicted is None else point("predicted", predicted)
    th1 = th0 if predicted_angle is None else number("predicted_angle", predicted_angle)
    min_alpha = number("min_alpha", min_alpha, nonnegative=True)
    if not min_alpha < 90:
        raise ValueError(f"min_alpha must be below 90 degrees, got {min_alpha!r}")
    opts = options.resolved(d)
    sin_alpha = abs(wedge(axis(th0), u))
    if sin_alpha < math.sin(math.radians(min_alpha)):
        return _rod_before(c1, th1, L, d, r_max, True, opts, "rod_after")
    return _rod_after(c0, th0, c1, th1, L, d, t, u, delta, sin_alpha, r_max, opts)


def crossing_t(centre, angle, L, t_pt, u, off) -> float:
    """Where on the line ``t_pt + off n + s u`` the rod's axis crosses (``s``), or its
    nearer end's ``s`` when the axis does not reach that line."""
    nv = perp(u)
    half = 0.5 * L * axis(angle)
    ends = [centre - half - t_pt, centre + half - t_pt]
    (pu, pn), (qu, qn) = [(float(e @ u), float(e @ nv)) for e in ends]
    if pn == qn or not min(pn, qn) <= off <= max(pn, qn):
        return pu if abs(pn - off) <= abs(qn - off) else qu
    return pu + (off - pn) / (qn - pn) * (qu - pu)


def _rod_after(c0, th0, c1, th1, L, d, t_pt, u, delta, sin_alpha, r_max, opts):
    pattern = "rod_after"
    nv = perp(u)
    step = L / 4 * sin_alpha
    limit = L + r_max
    reach = d + r_max + opts.margin
    queue = [0.0, float((c0 - t_pt) @ nv)] + list(step_offsets(step, limit))[1:]
    lines: list[LineOutcome] = []
    hits: list[tuple[float, LineOutcome]] = []
    touches: list[LineOutcome] = []
    scanned: list[float] = []
    while queue and len(hits) < 2:
        off = queue.pop(0)
        if abs(off) > limit or any(abs(off - s) < step / 4 for s in scanned):
            continue
        if len(lines) >= opts.max_lines:
            return missed(pattern, f"line budget of {opts.max_lines} used up", lines)
        ts = [crossing_t(c0, th0, L, t_pt, u, off), crossing_t(c1, th1, L, t_pt, u, off)]
        if not scanned:
            ts += [0.0, delta]
        s_lo, s_hi = min(ts) - reach, max(ts) + reach
        line = make_line(t_pt + off * nv, u, s_lo, s_hi, opts.spacing, f"L'{len(lines)}")
        out = yield from measure_line(line, ts[1] - s_lo, opts)
        lines.append(out)
        scanned.append(off)
        if not out.edges.found or not is_rod(out, d, opts):
            continue
        if out.edges.peak >= AXIS_PEAK * opts.height:
            hits.append((off, out))
        else:                                   # grazed an end: an outline point, no axis point
            touches.append(out)
        if len(hits) + len(touches) == 1:       # look next to it, toward the predicted centre
            side = 1.0 if float((c1 - t_pt) @ nv) >= off else -1.0
            queue = [off + side * step, off - side * step] + queue
    if len(hits) < 2:
        if hits or touches:
            return (yield from _fallback(pattern, lines, th1, L, d, opts))
        return missed(pattern, f"no line found the rod within L + r_max = {limit:g} nm of the "
                      f"push point ({len(lines)} lines)", lines)
    cross = [h for _, h in sorted(hits, key=lambda h: h[0])]
    w = axis_through(cross, axis(th1))
    result = None if w is None else (yield from finish_rod(pattern, cross, w, c1, th1, L, d,
                                                            r_max, opts, False, lines, "'",
                                                            touches))
    if result is not None and result.found:
        return result
    return (yield from _fallback(pattern, lines, th1, L, d, opts))


def _fallback(pattern, lines, th_ref, L, d, opts):
    """Cross lines at right angles to the longest chord seen, through the mean of all
    crossings seen: :func:`rod_before` with ``measure_angle``, once."""
    found = [o for o in lines if o.edges.found]
    if not found:
        return missed(pattern, "no line found the rod", lines)
    centre = np.concatenate([o.crossings() for o in found]).mean(axis=0)
    along = max(found, key=lambda o: o.edges.width).line.direction
    angle = near_angle(math.degrees(math.atan2(along[1], along[0])), th_ref)
    result = yield from _rod_before(centre, angle, L, d, L / 2, True, opts, pattern, lines,
                                    fallback=False)
    if result.found:
        return result
    return missed(pattern, f"the lines did not fix the rod's outline ({result.reason})", lines)


def axis_through(cross: list[LineOutcome], ref_axis: np.ndarray) -> np.ndarray | None:
    """Unit vector from the first to the second crossing midpoint, turned to ``ref_axis``."""
    w = cross[1].midpoint() - cross[0].midpoint()
    norm = math.hypot(*w)
    if not norm > 0:
        return None
    w = w / norm
    return -w if w @ ref_axis < 0 else w


def _axis_line(mids, w, ref, L, r_max, opts, role):
    """Line along ``w`` through ``mids[0]`` spanning every place of a rod of length ``L``
    that contains all ``mids`` and whose centre is (if that is consistent) within
    ``r_max`` of ``ref``. Returns the line and where ``mids[0]`` lies on it (nm from a)."""
    ts = [float((m - ref) @ w) for m in mids]
    lo, hi = max(ts) - L / 2, min(ts) + L / 2
    if max(lo, -r_max) <= min(hi, r_max):
        lo, hi = max(lo, -r_max), min(hi, r_max)
    origin = mids[0] - ts[0] * w
    s_lo = lo - L / 2 - opts.margin
    line = make_line(origin, w, s_lo, hi + L / 2 + opts.margin, opts.spacing, role)
    return line, ts[0] - s_lo


def _fit_lines(outcomes, c0, w, half0, rad0, fix_angle, end=None):
    """The outline through the crossings of ``outcomes``; with ``end`` (a line's one clear
    crossing: point, line direction, 1-σ), through it too at the half-length ``half0``."""
    pts = np.concatenate([o.crossings() for o in outcomes])
    dirs = np.repeat([o.line.direction for o in outcomes], 2, axis=0)
    stds = np.array([s for o in outcomes for s in (o.edges.left_std, o.edges.right_std)])
    if end is not None:
        pts, dirs, stds = np.vstack([pts, end[0]]), np.vstack([dirs, end[1]]), np.append(stds, end[2])
    ang = math.degrees(math.atan2(w[1], w[0]))
    return fit_capsule(pts, dirs, stds, c0, ang, half0, rad0, fix_angle=fix_angle, fix_half=end is not None)


def _misses_ends(line: ScanLine, fit) -> bool:
    """Whether ``line`` passes an end of the fitted core farther than half its radius."""
    a_hat = axis(fit.angle)
    nrm = perp(line.direction)
    ends = [fit.centre - fit.half * a_hat, fit.centre + fit.half * a_hat]
    return max(abs(float((e - np.asarray(line.a)) @ nrm)) for e in ends) > 0.5 * fit.radius


def _one_end(pattern, cross, touches, vline, vout, w, th_ref, L, d, rad0, fix_angle, lines, opts):
    """The outline from the cross lines and the one end line V saw clear (the other ran
    into a touching neighbour or off the line), at the believed length: the rod's
    length is not measured (``length_std`` None)."""
    # without the other end's check of the length, every cross line must be the rod's
    # height: one that crossed a particle beside the rod would tilt the axis
    share = max(ONE_END_HEIGHT, opts.rod_height or 0.0)
    if any(abs(o.edges.peak - d) > share * d + 3 * o.edges.noise for o in (*cross, *touches)
           if o.edges.peak is not None):
        return missed(pattern, f"line V along the rod saw one end only ({vout.edges.reason}), and a cross "
                      f"line is not of the rod's height", lines)
    at, std, side = vout.edges.end
    end_pt = vline.at(at)
    half = (L - d) / 2
    c0 = end_pt - side * (half + rad0) * vline.direction
    fit = _fit_lines([*cross, *touches], c0, w, half, rad0, fix_angle, end=(end_pt, vline.direction, std))
    if fit is None:
        return missed(pattern, f"line V along the rod saw one end only ({vout.edges.reason}), and the "
                      f"crossings do not place the rod by it", lines)
    return _result(pattern, fit, th_ref, d, fix_angle, lines, L, None, "one end seen; ")


def _result(pattern, fit, th_ref, d, fix_angle, lines, length, length_std, note=""):
    """The scan's result from an outline fit, refused where it hardly fixes the rod."""
    cov = fit.cov
    angle_std = None if fix_angle else float(math.sqrt(max(cov[2, 2], 0.0)))
    centre_std = math.sqrt(max(np.linalg.eigvalsh(cov[:2, :2])[-1], 0.0))
    if centre_std > d / 2 or (angle_std is not None and angle_std > MAX_ANGLE_STD):
        return missed(pattern, f"{note}the crossings hardly determine the rod's outline (centre "
                      f"1-sigma {centre_std:.3g} nm)", lines)
    return LocalScanResult(pattern, True, "found", (float(fit.centre[0]), float(fit.centre[1])),
                           cov[:2, :2].copy(), near_angle(fit.angle, th_ref), angle_std, length,
                           length_std, tuple(lines))


def finish_rod(pattern, cross, w, ref, th_ref, L, d, r_max, opts, fix_angle, lines, prime,
                touches=()):
    """Scan the axis line V through the cross lines' midpoints and fit the outline to
    their crossings, V's and those of lines that only grazed an end (``touches``)."""
    vline, s_exp = _axis_line([o.midpoint() for o in cross], w, ref, L, r_max, opts, "V" + prime)
    vout = yield from measure_line(vline, s_exp, opts)
    lines.append(vout)
    rad0 = float(np.mean([o.edges.width * abs(wedge(o.line.direction, w))
                          for o in cross])) / 2
    if not vout.edges.found:
        if vout.edges.end is None:
            return missed(pattern, f"line V{prime} along the rod found no ends ({vout.edges.reason})",
                          lines)
        return _one_end(pattern, cross, touches, vline, vout, w, th_ref, L, d, rad0, fix_angle, lines, opts)
    c0 = vline.at(vout.edges.centre)
    used = [*cross, *touches, vout]
    fit = _fit_lines(used, c0, w, vout.edges.width / 2 - rad0, rad0, fix_angle)
    if fit is not None and not fix_angle and _misses_ends(vline, fit) \
            and len(lines) < opts.max_lines:
        w2 = axis(fit.angle)
        line2, s2 = _axis_line([fit.centre], w2, ref, L, r_max, opts, "V" + prime + "2")
        out2 = yield from measure_line(line2, s2, opts)
        lines.append(out2)
        if out2.edges.found:
            used.append(out2)
            fit = _fit_lines(used, fit.centre, w2, fit.half, fit.radius, False)
    if fit is None:
        return missed(pattern, "the crossings do not determine the rod's outline", lines)
    length = 2 * fit.half + d
    if abs(length - L) > max(opts.length_tolerance * L, d):
        return missed(pattern, f"the fitted outline is {length:.4g} nm long, not about the "
                      f"believed {L:.4g} nm", lines)
    return _result(pattern, fit, th_ref, d, fix_angle, lines, length, 2 * float(math.sqrt(max(fit.cov[3, 3], 0.0))))
