"""A rod's scan after a push, placed where the pivot model puts the rod (issue 16: scans
chosen by what is uncertain).

The seed's pattern after a push (:func:`~.rod_scan.rod_after`, Fig. 5.2 right) runs its
lines along the push from behind where the rod started to beyond where it should be:
each is the push's length plus twice the reach, because it must find a rod that did not
move (the tip slipped) as surely as one that did. A rod pushed as predicted needs only
the reach about its predicted place. So this pattern first scans two lines along the push,
each ``d + r_max + margin`` to either side of where the predicted axis crosses it, at
half-way from the predicted centre to either end of its straight part (across the push),
then the seed's line V along the axis through their midpoints and the outline fit. Where
either short line misses the rod's crest, or the fit is refused, the seed's pattern runs
after them, whole: a rod that did not go where the model said is found as before, at the
cost of the short lines.

On the rods family (seed 1) the seed's pattern took four lines, 715, 442, 292 and 683 nm,
4.9 s, after each 323 nm push of a 500 nm rod; this one three, about 300, 300 and 680 nm.
"""

from __future__ import annotations

import math
from dataclasses import replace

from nanoasm.param import number

from .rod_outline import finish_rod
from .rod_scan import Pattern, axis_through, crossing_t, is_rod, rod_after, rod_args
from .scan_lines import AXIS_PEAK, DEFAULT_OPTIONS, ScanOptions, axis, make_line, measure_line, perp, point, unit, \
    wedge

#: Where the short lines cross the predicted rod: this share of its straight part's
#: half-length from its centre, to either side (across the push).
SPREAD = 0.5


def rod_after_predicted(start, start_angle: float, length: float, diameter: float, push_point,
                        push_direction, push_length: float, r_max: float, *, predicted,
                        predicted_angle: float, min_alpha: float = 15.0,
                        options: ScanOptions = DEFAULT_OPTIONS) -> Pattern:
    """Find a rod's pose after a push, first where the push model predicts it
    (``predicted``, ``predicted_angle``), then, if it is not there, by the seed's
    pattern (:func:`~.rod_scan.rod_after`, the same arguments). ``r_max`` is the largest
    expected error of the predicted pose (nm)."""
    _, _, L, d, r_max = rod_args(start, start_angle, length, diameter, r_max, ("start", "start_angle"))
    t = point("push_point", push_point)
    u = unit("push_direction", push_direction)
    c1 = point("predicted", predicted)
    th1 = number("predicted_angle", predicted_angle)
    opts = options.resolved(d)
    lines = []
    sin1 = abs(wedge(axis(th1), u))
    if sin1 >= math.sin(math.radians(min_alpha)):      # else the lines would run nearly along the rod
        nv = perp(u)
        mid = float((c1 - t) @ nv)
        q = SPREAD * 0.5 * (L - d) * sin1
        reach = d + r_max + opts.margin
        cross = []
        for off in (mid - q, mid + q):
            s = crossing_t(c1, th1, L, t, u, off)
            out = yield from measure_line(make_line(t + off * nv, u, s - reach, s + reach, opts.spacing,
                                                    f"P{len(lines)}"), reach, opts)
            lines.append(out)
            if not (out.edges.found and is_rod(out, d, opts) and out.edges.peak >= AXIS_PEAK * opts.height):
                break
            cross.append(out)
        w = axis_through(cross, axis(th1)) if len(cross) == 2 else None
        if w is not None:
            result = yield from finish_rod("rod_after", cross, w, c1, th1, L, d, r_max, opts, False, lines, "'")
            if result.found:
                return result
    result = yield from rod_after(start, start_angle, length, diameter, push_point, push_direction, push_length,
                                  r_max, predicted=predicted, predicted_angle=predicted_angle,
                                  min_alpha=min_alpha, options=options)
    return replace(result, lines=(*lines, *result.lines))
