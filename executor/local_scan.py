"""Local scan patterns before and after every push (seed ch. 5, Figs. 5.1 and 5.2).

Each pattern is a plan in the bluesky sense: a generator that yields
:class:`~nanoasm.executor.scan_lines.ScanLine` requests and is sent back the height
profile of each; it returns a :class:`~nanoasm.executor.scan_lines.LocalScanResult`
(the value of its ``StopIteration``)::

    pattern = particle_before(centre, diameter, r_max)
    line = next(pattern)
    try:
        while True:
            line = pattern.send(instrument.scan_line(line.a, line.b, line.n))
    except StopIteration as stop:
        result = stop.value

(:func:`run_pattern` does exactly this.) The rod patterns live in
:mod:`~nanoasm.executor.rod_scan` (importable from here too) and the widening search
for a lost object in :mod:`~nanoasm.executor.lost_search`. Arguments are checked when
the pattern is made, before any line is asked for. The sample is taken as still during
one pattern (a few lines, seconds); drift between patterns is the drift filter's.

``r_max`` is the largest expected error of the position the pattern starts from (nm),
e.g. :meth:`~nanoasm.drift.DriftFilter.r_max`; after a push it must also cover the push
model's error. A good estimate buys short lines and few search steps.
"""

from __future__ import annotations

from collections.abc import Generator
from dataclasses import replace

import numpy as np

from nanoasm.param import number

from .edges import TOUCHING
from .rod_scan import rod_after, rod_before
from .scan_lines import (AXIS_PEAK, DEFAULT_OPTIONS, LineOutcome, LocalScanResult, ScanLine,
                         ScanOptions, frame_cov, line_length, make_line, measure_line, missed, perp,
                         point, run_pattern, step_offsets, unit)

Pattern = Generator[ScanLine, np.ndarray, LocalScanResult]

__all__ = ["LineOutcome", "LocalScanResult", "Pattern", "ScanLine", "ScanOptions",
           "centre_from_hit", "line_length", "particle_after", "particle_after_predicted", "particle_before",
           "rod_after",
           "rod_before", "run_pattern"]


# ---------------------------------------------------------------- particles (Fig. 5.1)

def particle_before(centre, diameter: float, r_max: float, *, direction=(1.0, 0.0),
                    options: ScanOptions = DEFAULT_OPTIONS) -> Pattern:
    """Find a particle's centre before a push (seed 5.2, Fig. 5.1 left).

    Line L0 runs through the believed centre O along ``direction``; while it finds
    nothing it is moved alternately up and down by 3R/2 (L1, L2, ...) until it finds
    the particle or the lines cover ``r_max`` on both sides of O (if L0 alone covers
    that but saw the particle touching another one, the lines 3R/2 to either side are
    tried too). The edge crossings P1, P2 give a midpoint; line V through it,
    perpendicular, gives Q1, Q2; the centre is their midpoint. Each line reaches
    ``R + r_max + margin`` to both sides of O (the seed's ``l > R + r_max`` read as the
    reach either side; see :func:`line_length`).

    Parameters
    ----------
    centre : (2,) array-like
        Believed centre O (nm).
    diameter : float
        Particle diameter 2R (nm).
    r_max : float
        Largest expected error of ``centre`` (nm).
    direction : (2,) array-like
        Direction of L0.
    options : ScanOptions
    """
    o = point("centre", centre)
    d = number("diameter", diameter, positive=True)
    r_max = number("r_max", r_max, nonnegative=True)
    u = unit("direction", direction)
    opts = options.resolved(d)
    reach = d / 2 + r_max + opts.margin
    return _particle("particle_before", o, u, -reach, reach, 0.0, d, r_max, opts, "")


def particle_after(start, diameter: float, push_direction, push_length: float, r_max: float, *,
                   options: ScanOptions = DEFAULT_OPTIONS) -> Pattern:
    """Find a particle's centre after a push (seed 5.2, Fig. 5.1 right).

    As :func:`particle_before`, with line L'0 through the start centre O_a along the
    push, from ``R + r_max + margin`` behind O_a to as far beyond the pushed position
    O_a + Δ u: length ``Δ + 2(R + r_max + margin)``, the seed's ``l' > Δ + 2(R + r_max)``.
    Steps of 3R/2 across the push until found; V' across the push gives the centre.

    Parameters
    ----------
    start : (2,) array-like
        Centre O_a before the push (nm), as measured by :func:`particle_before`.
    diameter : float
    push_direction : (2,) array-like
        Direction of the push.
    push_length : float
        Δ (nm): the particle is expected at O_a + Δ u.
    r_max : float
        Largest expected error of that expected position (drift and push model, nm).
    options : ScanOptions
    """
    o, d, u, delta, r_max, opts, reach = _after_args(start, diameter, push_direction, push_length, r_max, options)
    return _particle("particle_after", o, u, -reach, delta + reach, delta, d, r_max, opts, "'")


def particle_after_predicted(start, diameter: float, push_direction, push_length: float, r_max: float, *,
                             options: ScanOptions = DEFAULT_OPTIONS) -> Pattern:
    """Find a particle's centre after a push, first where the push put it (issue 16:
    scans chosen by what is uncertain), then, if it is not there, by the seed's pattern
    (:func:`particle_after`, the same arguments).

    The seed's line L'0 runs from behind the start O_a to beyond O_a + Δ u, ``Δ + 2
    reach`` long, because it must find a particle the tip slipped off as surely as one
    pushed home. A particle pushed as predicted needs only the reach about O_a + Δ u: this
    pattern first scans that line, ``2 (R + r_max + margin)`` along the push (``P'0``),
    then V' across its chord's midpoint. Where P'0 finds nothing, or V' misses, the
    seed's pattern runs after it, whole: a particle that stopped short is found as before,
    at the cost of one short line.
    """
    o, d, u, delta, r_max, opts, reach = _after_args(start, diameter, push_direction, push_length, r_max, options)
    lines: list[LineOutcome] = []
    if delta > 0:                     # else the seed's line is this line
        out = yield from measure_line(make_line(o, u, delta - reach, delta + reach, opts.spacing, "P'0"),
                                      reach, opts)
        lines.append(out)
        if out.edges.found:
            result = yield from centre_from_hit("particle_after", out, -reach, reach, reach, d, opts, lines, "'")
            if result.found:
                return result
    result = yield from _particle("particle_after", o, u, -reach, delta + reach, delta, d, r_max, opts, "'")
    return replace(result, lines=(*lines, *result.lines))


def _after_args(start, diameter, push_direction, push_length, r_max, options: ScanOptions):
    """The after-scan's arguments checked: (O_a, d, u, Δ, r_max, resolved options, reach)."""
    d = number("diameter", diameter, positive=True)
    r_max = number("r_max", r_max, nonnegative=True)
    opts = options.resolved(d)
    return (point("start", start), d, unit("push_direction", push_direction),
            number("push_length", push_length, nonnegative=True), r_max, opts, d / 2 + r_max + opts.margin)


def _particle(pattern, origin, u, s_lo, s_hi, s_exp, d, r_max, opts, prime):
    v = perp(u)
    lines: list[LineOutcome] = []
    hit = None
    step = 0.75 * d
    offsets = list(step_offsets(step, r_max))
    for k, off in enumerate(offsets):          # the list may grow while it is walked
        if len(lines) >= opts.max_lines:
            return missed(pattern, f"line budget of {opts.max_lines} used up", lines)
        line = make_line(origin + off * v, u, s_lo, s_hi, opts.spacing, f"L{prime}{k}")
        out = yield from measure_line(line, s_exp - s_lo, opts)
        lines.append(out)
        if out.edges.found:
            hit = off, out
            break
        if out.edges.reason == TOUCHING and len(offsets) == 1:
            offsets += [step, -step]            # it is there, with a neighbour: step aside
    if hit is None:
        return missed(pattern, f"nothing within r_max = {r_max:g} nm ({len(lines)} lines)", lines)
    off, out = hit
    reach = d / 2 + r_max + opts.margin
    return (yield from centre_from_hit(pattern, out, -reach - off, reach - off, reach + off, d,
                                       opts, lines, prime))


def centre_from_hit(pattern, hit: LineOutcome, t_lo: float, t_hi: float, t_exp: float, d: float,
                    opts: ScanOptions, lines: list, prime: str = ""):
    """The seed's line V across ``hit`` through its chord's midpoint, from ``t_lo`` to
    ``t_hi`` (nm from that midpoint), the particle expected ``t_exp`` nm from V's start.

    A chord's midpoint is the centre's projection however far off-centre the line ran,
    but its precision falls as the line grazes the particle. If ``hit`` peaked below
    :data:`AXIS_PEAK` of the height, or was sampled coarser than ``opts.spacing``, one
    more line along ``hit`` through V's midpoint (``L*``) measures the centre along
    ``hit`` again.
    """
    u = hit.line.direction
    v = perp(u)
    vline = make_line(hit.midpoint(), v, t_lo, t_hi, opts.spacing, "V" + prime)
    vout = yield from measure_line(vline, t_exp, opts)
    lines.append(vout)
    if not vout.edges.found:
        return missed(pattern, f"line V{prime} through the midpoint found nothing "
                      f"({vout.edges.reason})", lines)
    centre = vline.at(vout.edges.centre)
    std_u = hit.edges.centre_std
    again_needed = hit.edges.peak < AXIS_PEAK * opts.height \
        or hit.line.spacing > 1.5 * opts.spacing
    if again_needed and len(lines) < opts.max_lines:
        reach = d / 2 + opts.margin + 3 * std_u
        line = make_line(centre, u, -reach, reach, opts.spacing, "L" + prime + "*")
        again = yield from measure_line(line, reach, opts)
        lines.append(again)
        if again.edges.found and again.edges.centre_std < std_u:
            centre, std_u = line.at(again.edges.centre), again.edges.centre_std
    cov = frame_cov(u, std_u, vout.edges.centre_std)
    return LocalScanResult(pattern, True, "found", (float(centre[0]), float(centre[1])), cov,
                           lines=tuple(lines))
