"""Local scans of fixed features: the step on one line across an edge, and the pattern of
lines across a feature's sites.

A local scan line along an :class:`~nanoasm.executor.fixed_features.EdgeSite`'s normal,
from the obstacle's top down to the substrate, finds the same half-height crossing the
full scan showed (:func:`locate_step`), the tip broadening the step the same way in
both; :func:`edge_pattern` scans one such line per site through the scan-pattern
protocol and turns them into offsets along the normals (:class:`EdgeScanResult`), and
:func:`pattern_samples` counts what it scans. Lengths in nm.
"""

from __future__ import annotations

import math
from collections.abc import Generator, Sequence
from dataclasses import dataclass

import numpy as np

from nanoasm.param import number

from .edges import _crossing, _merge, _runs
from .substrate import _check_profile, _robust_std
from .fixed_features import HEIGHT_TOLERANCE
from .scan_lines import ScanLine, make_line, point, unit

#: On a local line the step's 25-75 % rise may span at most this fraction of its height:
#: a steep wall seen by a usual tip spans 0.18 (10 nm tip of 20°, 30 nm step) to 0.33
#: (20 nm tip of 25°, 20 nm step) of it; a particle at its foot taller than half the step
#: makes a shoulder (0.45 for a 16 nm particle at a 30 nm step).
MAX_WIDTH = 0.4
#: A rise of the top or the step after a dip of more than this fraction of the step (or
#: of 3 noise rms, smoothed over three samples) is something on the line: a particle as
#: tall as the step at its foot leaves a dip of 2 nm (10 nm tip) between the two.
MAX_DIP = 0.05
#: Two sites of one edge agree when their offsets differ by less than this many sigmas.
CONSISTENT = 3.0


# ---------------------------------------------------------------- one local line

@dataclass(frozen=True)
class StepCrossing:
    """The half-height crossing of a step on one local line (high side first), or why not.

    Attributes
    ----------
    found : bool
    reason : str
        ``"found"``; ``"no step"``; ``"step rises along the line"``; ``"step height 12 nm,
        expected 30"``; ``"several crossings: something on the line"``; ``"step not
        monotone: something on the line"``; ``"step too gradual: something on the
        line"``; ``"step cut by the line end"``.
    position, std : float or None
        The crossing (nm from the line's start) and its 1-sigma (nm): the noise over the
        slope, the sampling, and the levels' uncertainty.
    step : float or None
        The step's height (nm): top level minus substrate level, at the crossing.
    noise : float
        Robust rms of the samples about the two levels (nm).
    """

    found: bool
    reason: str
    position: float | None = None
    std: float | None = None
    step: float | None = None
    noise: float = 0.0


def locate_step(profile, spacing: float, height: float, *, expected: float | None = None
                ) -> StepCrossing:
    """Where a line running from an obstacle's top down to the substrate crosses half
    the step's height.

    The top and the substrate are two parallel straight lines (a tilted line) fitted by
    least squares to the samples near each level, iterated with a 3-sigma band, so
    noise, roughness and the rounded top of the step do not pull them. The crossing is
    interpolated as in :func:`~nanoasm.executor.edges.find_edges` between the two
    samples that bracket half the step. Refused: no step, a step rising along the line,
    a step whose height is off by more than
    :data:`~nanoasm.executor.fixed_features.HEIGHT_TOLERANCE`, more crossings of
    half height (something else on the line), a dip on the top or within the step, a
    25-75 % rise wider than :data:`MAX_WIDTH` of the step (something at the step's
    foot), or fewer than four samples left on either level (the step cut by the line end).

    Parameters
    ----------
    profile : (n,) array
        Heights (nm) at ``n >= 5`` samples ``spacing`` apart.
    spacing : float
        Distance between samples (nm).
    height : float
        Expected step height (nm).
    expected : float, optional
        Where the step should be (nm from the start). Without it the line must cross
        half height once; with it, whatever rises past half height again on the
        substrate side is cut off (the line ends before it), provided the step's fall
        is the one nearest to ``expected``.

    Returns
    -------
    StepCrossing
        Never raises for a finite profile.
    """
    z = _check_profile(profile)
    h = number("spacing", spacing, positive=True)
    height = number("height", height, positive=True)
    if expected is not None:
        expected = number("expected", expected)
    n = z.size
    noise = _robust_std(np.diff(z)) / math.sqrt(2)
    lo0, hi0 = np.percentile(z, [10, 90])
    if hi0 - lo0 < max(8 * noise, 0.25 * height):
        return StepCrossing(False, "no step", noise=noise)
    runs = _merge(_runs(z > 0.5 * (lo0 + hi0)), z, 0.5 * (lo0 + hi0) - 4 * noise)
    end = _segment(runs, n, expected, h)
    if isinstance(end, str):
        return StepCrossing(False, end, noise=noise)
    z = z[:end]
    fit = _levels(z, runs[0][1], hi0 - lo0)
    if fit is None:
        return StepCrossing(False, "step cut by the line end", noise=noise)
    base, step, cov, noise = fit
    y = z - base
    level = 0.5 * step
    if not abs(step - height) <= HEIGHT_TOLERANCE * height:
        return StepCrossing(False, f"step height {step:.0f} nm, expected {height:g}", step=step,
                            noise=noise)
    runs = _merge(_runs(y > level), y, level - 4 * noise)
    if len(runs) != 1 or runs[0][0] != 0 or runs[0][1] >= z.size - 1:
        return StepCrossing(False, "several crossings: something on the line", step=step, noise=noise)
    j = runs[0][1]
    shape = _shape(y, j, step, noise, h)
    if shape:
        return StepCrossing(False, shape, step=step, noise=noise)
    pos, std = _crossing(y, j + 1, j, level, h, noise)
    g = np.array([1.0, pos / h, 0.5])                   # d(half-step level)/d(coefficients)
    slope = (y[j] - y[j + 1]) / h
    std = math.hypot(std, math.sqrt(max(g @ cov @ g, 0.0)) / slope)
    return StepCrossing(True, "found", float(pos), float(std), float(step), float(noise))


def _segment(runs: list[tuple[int, int]], n: int, expected: float | None, h: float) -> int | str:
    """How many samples from the start hold the step (the line cut before anything that
    rises again past half height beyond it), or why the line holds no usable step."""
    if not runs or runs[0][0] > 0:
        return "step rises along the line" if runs and runs[-1][1] == n - 1 else "no step"
    if runs[0][1] == n - 1:
        return "no step"
    if len(runs) == 1:
        return n
    if expected is None:
        return "several crossings: something on the line"
    falls = [(j + 0.5) * h for _, j in runs if j < n - 1]
    if min(falls, key=lambda f: abs(f - expected)) != falls[0]:
        return "several crossings: something on the line"
    return runs[1][0]


def _levels(z: np.ndarray, j: int, delta: float):
    """Substrate line and step height fitted to the samples near each level.

    Returns ``(base (n,), step, cov (3, 3), noise)`` with ``cov`` the covariance of
    (intercept, slope per sample, step), or None when either level keeps fewer than four
    samples."""
    n = z.size
    x = np.arange(n, dtype=float)
    top = x <= j
    a = np.column_stack([np.ones(n), x, top.astype(float)])
    hi = np.median(z[:j + 1][z[:j + 1] > np.percentile(z, 90) - 0.2 * delta])
    lo = np.median(z[j + 1:][z[j + 1:] < np.percentile(z, 10) + 0.2 * delta])
    model = np.where(top, hi, lo)
    band = 0.2 * delta
    for _ in range(4):
        sel = np.abs(z - model) < band
        if (sel & top).sum() < 4 or (sel & ~top).sum() < 4:
            return None
        coef, *_ = np.linalg.lstsq(a[sel], z[sel], rcond=None)
        model = a @ coef
        r = z[sel] - model[sel]
        sigma = max(_robust_std(r), 1e-9)
        band = max(3.5 * sigma, 1e-6 * delta)
    ata = a[sel].T @ a[sel]
    cov = sigma ** 2 * np.linalg.inv(ata)
    return coef[0] + coef[1] * x, float(coef[2]), cov, float(sigma)


def _shape(y: np.ndarray, j: int, step: float, noise: float, h: float) -> str:
    """Why the fall after sample ``j`` is not one steep step (empty when it is)."""
    n = y.size
    a = j
    while a > 0 and y[a - 1] < 0.9 * step:
        a -= 1
    b = j + 1
    while b < n - 1 and y[b + 1] > 0.1 * step:
        b += 1
    top = np.convolve(y[:b + 1], np.ones(3) / 3, "valid")          # noise / sqrt(3)
    if top.size and (top - np.minimum.accumulate(top)).max() > max(3 * noise, MAX_DIP * step):
        return "step not monotone: something on the line"
    seg = y[a:b + 1]
    if (_first_below(seg, 0.25 * step) - _first_below(seg, 0.75 * step)) * h > MAX_WIDTH * step:
        return "step too gradual: something on the line"
    return ""


def _first_below(seg: np.ndarray, level: float) -> float:
    """Fractional index where the falling ``seg`` first drops to ``level``."""
    k = int(np.argmax(seg <= level))
    if k == 0:
        return 0.0
    return k - 1 + (seg[k - 1] - level) / (seg[k - 1] - seg[k])


# ---------------------------------------------------------------- the local scan pattern

@dataclass(frozen=True, eq=False)
class EdgeScanResult:
    """Outcome of :func:`edge_pattern`.

    Attributes
    ----------
    found : bool
        Every line found its step and (two sites of one edge) their offsets agree.
    offsets : (m,) array
        How far along each site's normal the measured crossing lies from the site's
        point (nm; NaN where not found).
    stds : (m,) array
        Their 1-sigma (nm): the line's, and the site's own when given.
    ok : (m,) bool array
        Which lines found their step.
    reason : str
        ``"found"``, or the first line's failure, or the disagreement of two sites.
    lines, samples : int
        Lines scanned and their samples (instrument time).
    steps : tuple of StepCrossing
        What each line found.
    line_creep : (m, 2) array or None
        The creep (nm, nominal amplitude) each line was shifted by to compensate for
        the time since the first (the run's; see
        :meth:`~nanoasm.executor.scan_lines.LocalScanResult.creep_sensitivity`).
    """

    found: bool
    offsets: np.ndarray
    stds: np.ndarray
    ok: np.ndarray
    reason: str
    lines: int
    samples: int
    steps: tuple[StepCrossing, ...] = ()
    line_creep: np.ndarray | None = None


def edge_pattern(sites_scanner: Sequence, reach: float, *, spacing: float = 1.0,
                 height: float | None = None, site_stds=None, agree: bool = True
                 ) -> Generator[ScanLine, np.ndarray, EdgeScanResult]:
    """Scan one line across each edge site and measure how far its step has moved.

    A scan pattern as in :mod:`~nanoasm.executor.local_scan` (drive it with
    :func:`~nanoasm.executor.scan_lines.run_pattern`): line ``k`` runs from
    ``point - reach normal`` to ``point + reach normal`` (from the top down to the
    substrate) with samples about ``spacing`` apart, and :func:`locate_step` finds its
    crossing. Two sites with parallel normals on one line (an edge feature) must agree
    within :data:`CONSISTENT` sigmas; otherwise something on one of them moved the step.

    Parameters
    ----------
    sites_scanner : sequence of (point, normal, height)
        Each site's point already placed in the scanner frame (nm), its unit normal and
        its step height (nm), e.g. from an :class:`EdgeSite` and the drift estimate.
    reach : float
        Half-length of each line (nm): the largest expected position error plus room
        for the step's broadening and for both levels (e.g. ``r_max + 40``).
    spacing : float
        Largest distance between samples (nm).
    height : float, optional
        Expected step height for every line; each site's own by default.
    site_stds : float or (m,) array, optional
        1-sigma of the sites' points along their normals (nm, :attr:`EdgeSite.std`):
        added to each line's std, so the offsets' stds and the agreement test hold it.
    agree : bool
        Whether two sites of one edge must agree (False when their points may still
        differ by an unknown amount, e.g. the drift between their full-scan rows).

    Returns
    -------
    generator
        Yields :class:`ScanLine` requests, is sent each profile ((n,) array), returns an
        :class:`EdgeScanResult`. Arguments are checked before the first line.
    """
    sites = [_scanner_site(k, s) for k, s in enumerate(sites_scanner)]
    if not sites:
        raise ValueError("sites_scanner must hold at least one (point, normal, height)")
    reach = number("reach", reach, positive=True)
    spacing = number("spacing", spacing, positive=True)
    if height is not None:
        height = number("height", height, positive=True)
    extra = np.zeros(len(sites)) if site_stds is None else np.broadcast_to(
        np.asarray(site_stds, float), (len(sites),)).copy()
    if not (np.all(np.isfinite(extra)) and np.all(extra >= 0)):
        raise ValueError(f"site_stds must be non-negative and finite, got {site_stds!r}")
    return _edge_lines(sites, reach, spacing, height, extra, bool(agree))


def _scanner_site(k: int, site) -> tuple[np.ndarray, np.ndarray, float]:
    try:
        p, n, h = site
    except (TypeError, ValueError):
        raise ValueError(f"sites_scanner[{k}] must be (point, normal, height), got {site!r}") from None
    return (point(f"sites_scanner[{k}] point", p), unit(f"sites_scanner[{k}] normal", n),
            number(f"sites_scanner[{k}] height", h, positive=True))


def _edge_lines(sites, reach, spacing, height, extra, agree):
    m = len(sites)
    offsets, stds, ok = np.full(m, np.nan), np.full(m, np.nan), np.zeros(m, bool)
    steps, samples = [], 0
    for k, (p, n, h) in enumerate(sites):
        line = make_line(p, n, -reach, reach, spacing, f"E{k}")
        profile = np.asarray((yield line), dtype=float)
        if profile.shape != (line.n,):
            raise ValueError(f"profile for line {line.role} must have shape ({line.n},), "
                             f"got {profile.shape}")
        samples += line.n
        step = locate_step(profile, line.spacing, h if height is None else height, expected=reach)
        steps.append(step)
        if step.found:
            ok[k] = True
            offsets[k] = step.position - reach
            stds[k] = math.hypot(step.std, extra[k])
    reason = next((f"line E{k}: {s.reason}" for k, s in enumerate(steps) if not s.found), "found")
    if reason == "found" and agree:
        reason = _disagreement(sites, offsets, stds)
    return EdgeScanResult(reason == "found", offsets, stds, ok, reason, m, samples, tuple(steps))


def _disagreement(sites, offsets: np.ndarray, stds: np.ndarray) -> str:
    """Why two sites of one straight edge disagree ("found" when every such pair agrees)."""
    for a in range(len(sites)):
        for b in range(a + 1, len(sites)):
            (pa, na, _), (pb, nb, _) = sites[a], sites[b]
            if np.dot(na, nb) < math.cos(math.radians(5.0)):
                continue
            if abs(np.dot(pb - pa, na)) > 0.05 * math.hypot(*(pb - pa)) + 5.0:
                continue                      # parallel, but not one edge
            diff = abs(offsets[a] - offsets[b])
            if diff > CONSISTENT * math.hypot(stds[a], stds[b]):
                return (f"sites E{a} and E{b} of one edge disagree by {diff:.1f} nm "
                        f"(sigma {math.hypot(stds[a], stds[b]):.1f}): something on the edge")
    return "found"


def pattern_samples(reach: float, spacing: float, m: int) -> int:
    """Samples :func:`edge_pattern` scans for ``m`` sites (its cost in instrument time:
    divide by the line rate's samples per second)."""
    reach = number("reach", reach, positive=True)
    spacing = number("spacing", spacing, positive=True)
    m = number("m", m, integer=True, lo=0)
    return m * make_line(np.zeros(2), np.array([1.0, 0.0]), -reach, reach, spacing, "").n
