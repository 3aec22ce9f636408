"""Widening search for an object that a local scan did not find.

A raster of parallel lines, 3R/2 apart (the seed's step for particles, ch. 5), covers a
square around the last known position; the square's half-size doubles from ``start``
until it reaches ``radius``. Each stage scans only what the previous ones have not: new
offsets get full lines, old offsets get the two new end pieces, each overlapping the
covered part by an object's width plus the margin, so an object on the old boundary is
seen whole on one of them. The search stops at the first line with an object on it.

Any object within the square crosses some line: a disc of diameter d or a rod of that
diameter is at least d wide across every line direction, more than the 3d/4 between lines.
"""

from __future__ import annotations

import math
from collections.abc import Generator, Iterator
from dataclasses import dataclass

import numpy as np

from nanoasm.param import number

from .local_scan import centre_from_hit
from .scan_lines import (DEFAULT_OPTIONS, LineOutcome, LocalScanResult, ScanLine, ScanOptions,
                         _Accounting, make_line, measure_line, missed, perp, point, unit)


@dataclass(frozen=True, eq=False)
class SearchResult(_Accounting):
    """Outcome of :func:`search_lost`.

    Attributes
    ----------
    found : bool
    reason : str
    point : (x, y) or None
        Midpoint of the first crossing found: a point on the object (nm). For a
        particle it lies on the centre's line across the scan; for a rod, on its axis
        if the line crossed the rod's straight part.
    hit : LineOutcome or None
        The line that found it (its edges give the chord and peak height, by which the
        caller can tell whether this is the object it lost).
    lines : tuple of LineOutcome
    """

    found: bool
    reason: str
    point: tuple[float, float] | None = None
    hit: LineOutcome | None = None
    lines: tuple[LineOutcome, ...] = ()


def _alternating(j_max: int) -> Iterator[int]:
    yield 0
    for j in range(1, j_max + 1):
        yield j
        yield -j


def raster_segments(diameter: float, radius: float, start: float, margin: float
                    ) -> Iterator[tuple[float, float, float]]:
    """``(offset, s0, s1)`` of every search line, in scanning order.

    Offsets are across the raster direction and ``s0 < s1`` along it, all relative to
    the last known position (nm). Every point of the square of half-size ``radius``
    lies within 3/8 of a diameter of a line, and half a diameter inside its ends.
    """
    step = 0.75 * diameter
    ext = diameter + margin
    r_prev, j_prev, r = None, -1, min(start, radius)
    while True:
        j_max = math.ceil(max(r - step / 2, 0.0) / step - 1e-9)   # lines reach r + step/2
        for j in _alternating(j_max):
            off = j * step
            if abs(j) <= j_prev:
                yield off, -r - ext, -r_prev + ext
                yield off, r_prev - ext, r + ext
            else:
                yield off, -r - ext, r + ext
        if r >= radius:
            return
        r_prev, j_prev, r = r, j_max, min(2 * r, radius)


def _args(last_known, diameter, radius, direction, start, spacing, options):
    o = point("last_known", last_known)
    d = number("diameter", diameter, positive=True)
    radius = number("radius", radius, nonnegative=True)
    u = unit("direction", direction)
    start = 2 * d if start is None else number("start", start, positive=True)
    opts = options.resolved(d)
    spacing = max(opts.spacing, d / 8) if spacing is None else number("spacing", spacing, positive=True)
    return o, d, radius, u, start, spacing, opts


def search_lost(last_known, diameter: float, radius: float, *, direction=(1.0, 0.0),
                start: float | None = None, spacing: float | None = None,
                options: ScanOptions = DEFAULT_OPTIONS
                ) -> Generator[ScanLine, np.ndarray, SearchResult]:
    """Search a growing square around ``last_known`` for an object of ``diameter``.

    Parameters
    ----------
    last_known : (2,) array-like
        Where the object was last seen or believed (nm).
    diameter : float
        Its diameter (nm); lines are 3/4 of it apart.
    radius : float
        Half-size of the largest square searched (nm).
    direction : (2,) array-like
        Direction of the raster lines.
    start : float, optional
        Half-size of the first square (nm); twice the diameter when not given.
    spacing : float, optional
        Sample spacing of the search lines (nm); they only need to see the object, so
        an eighth of its diameter (or ``options.spacing`` if coarser) when not given.
    options : ScanOptions
        ``max_lines`` bounds the search; raise it for a wide one.

    Returns
    -------
    generator
        Yields ScanLine requests, is sent their profiles, returns a SearchResult.
    """
    args = _args(last_known, diameter, radius, direction, start, spacing, options)
    return _search(*args)


def _search(o, d, radius, u, start, spacing, opts):
    v = perp(u)
    lines: list[LineOutcome] = []
    for off, s0, s1 in raster_segments(d, radius, start, opts.margin):
        if len(lines) >= opts.max_lines:
            return SearchResult(False, f"line budget of {opts.max_lines} used up",
                                lines=tuple(lines))
        line = make_line(o + off * v, u, s0, s1, spacing, f"S{len(lines)}")
        out = yield from measure_line(line, -s0, opts)
        lines.append(out)
        if out.edges.found:
            m = out.midpoint()
            return SearchResult(True, "found", (float(m[0]), float(m[1])), out, tuple(lines))
    return SearchResult(False, f"nothing within {radius:g} nm ({len(lines)} lines)",
                        lines=tuple(lines))


def find_lost_particle(last_known, diameter: float, radius: float, *, direction=(1.0, 0.0),
                       start: float | None = None, spacing: float | None = None,
                       options: ScanOptions = DEFAULT_OPTIONS
                       ) -> Generator[ScanLine, np.ndarray, LocalScanResult]:
    """:func:`search_lost`, then a line across the hit through its midpoint (the seed's V):
    the particle's centre, as :func:`~nanoasm.executor.local_scan.particle_before` gives it.

    The result's ``pattern`` is ``"lost_particle"``; it may be another particle than the
    one lost, which the caller judges (by size, or by the drift filter's gate).
    """
    args = _args(last_known, diameter, radius, direction, start, spacing, options)
    return _find_particle(*args)


def _find_particle(o, d, radius, u, start, spacing, opts):
    pattern = "lost_particle"
    found = yield from _search(o, d, radius, u, start, spacing, opts)
    lines = list(found.lines)
    if not found.found:
        return missed(pattern, found.reason, lines)
    reach = d + opts.margin
    return (yield from centre_from_hit(pattern, found.hit, -reach, reach, reach, d, opts, lines))
