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

from .capsule_fit import near_angle
from .rod_outline import finish_rod
from .scan_lines import (AXIS_PEAK, DEFAULT_OPTIONS, LineOutcome, LocalScanResult, ScanLine,
                         ScanOptions, axis, make_line, measure_line, missed, perp, point, step_offsets,
                         unit, wedge)

Pattern = Generator[ScanLine, np.ndarray, LocalScanResult]



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
