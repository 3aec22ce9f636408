"""Fixed features for drift: straight obstacle edges and sharp corners.

Electrodes and pads never move, so where their straight edges lie measures the drift
after every object has been pushed (Li, Wang and Liu, IEEE T-ASE 2012: local scans of
one fixed feature). A straight edge measures one coordinate, the one along its normal;
a sharp corner, through one site on each of its two edges, measures both.

An :class:`EdgeSite` is where the half-height crossing of a step lies, found in the full
scan (:func:`find_features`) to sub-pixel precision; a local scan line along the site's
normal finds the same crossing again (:func:`locate_step`), the tip broadening the step
the same way in both, and :func:`edge_pattern` turns the lines into offsets along the
normals. Lengths in nm; ``row`` is an image row index (row 0 at the bottom, scanned first).

In the full scan the crossing is read off the image along profiles across the edge,
bilinear between pixel centres, so the pixel phase biases it. Measured on rendered edges
at 10 nm pixels, all angles and phases (rms, max in nm): a 10 nm tip of 20° half angle
gives 0.52, 0.84 on a 30 nm step; 0.94, 1.7 on a 20 nm step; 0.04, 0.14 on a 50 nm step;
a 20 nm tip of 25° about the same; a sharp 2 nm tip of 10°, whose step the pixels do not
resolve, 1.5, 2.4 on a 30 nm step. A site's ``std`` holds :data:`PIXEL_FLOOR` of a pixel
for it, besides the spread of its profiles.
"""

from __future__ import annotations

import math
from collections.abc import Generator, Sequence
from dataclasses import dataclass

import numpy as np
import shapely
from scipy import ndimage

from nanoasm.instrument import HeightImage
from nanoasm.param import number

from .edges import _check_profile, _crossing, _merge, _robust_std, _runs
from .scan_lines import ScanLine, make_line, point, unit

KINDS = ("edge", "corner")
#: Profiles across the edge per full-scan site, one pixel apart along the edge.
BAND = 5
#: Step of the samples along a full-scan profile (pixels).
PROFILE_STEP = 0.25
#: Levels are taken between GAP and GAP + WIDTH from the edge, each the larger of
#: (pixels, nm): beyond the tip's broadening of the step and the polygon's error.
LEVEL_GAP = (3.0, 40.0)
LEVEL_WIDTH = (3.0, 30.0)
#: A site whose profiles' crossings stray further than this from their median (pixels) is
#: dropped: something sits on the edge there.
MAX_STRAY = 0.3
#: A step differing from the obstacle's height by more than this fraction is refused.
HEIGHT_TOLERANCE = 0.3
#: Pixel-phase error of a full-scan crossing (pixels, 1-sigma; see the module docstring).
PIXEL_FLOOR = 0.08
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


# ---------------------------------------------------------------- value types

@dataclass(frozen=True)
class EdgeSite:
    """Where the half-height crossing of a straight obstacle edge lies in the full scan.

    Attributes
    ----------
    point : (x, y)
        The crossing (nm, the image's frame = the layout frame).
    normal : (nx, ny)
        Unit normal of the edge, from the obstacle (high side) to the substrate.
    height : float
        Step height (nm) measured there.
    std : float
        1-sigma of the point's coordinate along ``normal`` (nm).
    row : float
        Mean image row index of the pixels the crossing was read from (the caller turns
        it into the time the row was scanned, to take out the drift during the scan).
    """

    point: tuple[float, float]
    normal: tuple[float, float]
    height: float
    std: float
    row: float

    def __post_init__(self) -> None:
        p = point("point", self.point)
        n = point("normal", self.normal)
        if abs(math.hypot(*n) - 1.0) > 1e-6:
            raise ValueError(f"normal must be a unit vector, got {self.normal!r}")
        object.__setattr__(self, "point", (float(p[0]), float(p[1])))
        object.__setattr__(self, "normal", (float(n[0]), float(n[1])))
        object.__setattr__(self, "height", number("height", self.height, positive=True))
        object.__setattr__(self, "std", number("std", self.std, positive=True))
        object.__setattr__(self, "row", number("row", self.row))


@dataclass(frozen=True)
class Feature:
    """A fixed feature: ``"edge"`` (two sites on one straight edge: one coordinate,
    checked twice) or ``"corner"`` (one site on each edge of a sharp corner: both)."""

    id: str
    kind: str
    obstacle: int
    sites: tuple[EdgeSite, ...]

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {self.kind!r}")
        if not isinstance(self.id, str) or not self.id:
            raise ValueError(f"id must be a non-empty string, got {self.id!r}")
        if not self.sites or not all(isinstance(s, EdgeSite) for s in self.sites):
            raise ValueError("sites must be a non-empty tuple of EdgeSite")
        object.__setattr__(self, "sites", tuple(self.sites))

    def normals(self) -> np.ndarray:
        """The sites' normals, (m, 2) array."""
        return np.array([s.normal for s in self.sites])


# ---------------------------------------------------------------- polygon sides

def _ring(poly: shapely.Polygon) -> np.ndarray:
    """The polygon's vertices, (N, 2), counter-clockwise, vertex 0 first."""
    ring = np.asarray(poly.exterior.coords, float)[:-1]
    x, y = ring[:, 0], ring[:, 1]
    if np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)) < 0:
        ring = np.roll(ring[::-1], 1, axis=0)
    return ring


def _straight_runs(ring: np.ndarray, tol: float) -> list[tuple[int, int]]:
    """Maximal runs of vertices ``(i, j)`` (indices modulo N, j after i) that stay within
    ``tol`` of their chord, starting at the sharpest vertex; together they go round."""
    n = len(ring)
    d_in = ring - np.roll(ring, 1, axis=0)
    d_out = np.roll(ring, -1, axis=0) - ring
    turn = np.abs(np.arctan2(d_in[:, 0] * d_out[:, 1] - d_in[:, 1] * d_out[:, 0],
                             np.sum(d_in * d_out, axis=1)))
    start = int(np.argmax(turn))
    runs, i = [], start
    while i < start + n:
        j = i + 1
        while j + 1 <= start + n and _within(ring, i, j + 1, tol):
            j += 1
        runs.append((i % n, j % n))
        i = j
    return runs


def _within(ring: np.ndarray, i: int, j: int, tol: float) -> bool:
    n = len(ring)
    a, b = ring[i % n], ring[j % n]
    d = b - a
    length = math.hypot(*d)
    if length == 0:
        return False
    mid = ring[[k % n for k in range(i + 1, j)]]
    if not len(mid):
        return True
    return bool(np.all(np.abs((mid - a) @ np.array([-d[1], d[0]])) / length <= tol))


def _on_border(a: np.ndarray, b: np.ndarray, image: HeightImage) -> bool:
    """Whether the side from ``a`` to ``b`` runs along the image's border (within a pixel)."""
    (x0, y0), (w, h) = image.origin, image.extent
    tol = image.pixel_size
    for k, lo, hi in ((0, x0, x0 + w), (1, y0, y0 + h)):
        for edge in (lo, hi):
            if abs(a[k] - edge) <= tol and abs(b[k] - edge) <= tol:
                return True
    return False


@dataclass(frozen=True, eq=False)
class _Side:
    """A straight side refined in the image: the half-height line ``q + t u`` (t in
    [0, length]) with outward normal ``n``."""

    q: np.ndarray
    u: np.ndarray
    n: np.ndarray
    length: float


# ---------------------------------------------------------------- profiles in the image

@dataclass(frozen=True, eq=False)
class _Scope:
    """What the profiles of one obstacle need: the image, sample offsets along the
    normal, the level windows, and where the top and the substrate may be read."""

    image: HeightImage
    s: np.ndarray
    gap: float
    inside: shapely.Geometry
    outside: shapely.Geometry

    def crossings(self, starts: np.ndarray, n: np.ndarray):
        """Half-height crossing of profiles from ``starts`` (k, 2) along ``n``: offsets
        (k,) from the starts along ``n`` (NaN where none), points (k, 2) and step
        heights (k,)."""
        pts = starts[:, None, :] + self.s[None, :, None] * n
        z, valid = _bilinear(self.image, pts)
        x, y = pts[..., 0], pts[..., 1]
        far = np.abs(self.s) >= self.gap
        top = valid & far[None] & (self.s < 0)[None] & shapely.contains_xy(self.inside, x, y)
        low = valid & far[None] & (self.s > 0)[None] & ~shapely.contains_xy(self.outside, x, y)
        k = len(starts)
        out = np.full(k, np.nan), np.full((k, 2), np.nan), np.full(k, np.nan)
        for i in range(k):
            if top[i].sum() < 3 or low[i].sum() < 3 or not valid[i, ~far].all():
                continue
            hi, lo = np.median(z[i, top[i]]), np.median(z[i, low[i]])
            c = _down_crossing(z[i], self.s, lo + 0.5 * (hi - lo), ~far)
            if c is None:
                continue
            out[0][i], out[2][i] = c, hi - lo
            out[1][i] = starts[i] + c * n
        return out


def _bilinear(image: HeightImage, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Heights at points ``(..., 2)`` (nm) between pixel centres, and where they are inside."""
    ps = image.pixel_size
    cols = (pts[..., 0] - image.origin[0]) / ps - 0.5
    rows = (pts[..., 1] - image.origin[1]) / ps - 0.5
    ny, nx = image.shape
    valid = (rows >= 0) & (rows <= ny - 1) & (cols >= 0) & (cols <= nx - 1)
    z = ndimage.map_coordinates(image.height, [rows.ravel(), cols.ravel()], order=1, mode="nearest")
    return z.reshape(rows.shape), valid


def _down_crossing(z: np.ndarray, s: np.ndarray, level: float, window: np.ndarray) -> float | None:
    """Where ``z`` falls through ``level`` within ``window``, if it does so exactly once."""
    above = z > level
    idx = np.nonzero(above[:-1] & ~above[1:] & window[:-1] & window[1:])[0]
    rises = np.nonzero(~above[:-1] & above[1:] & window[:-1] & window[1:])[0]
    if len(idx) != 1 or len(rises):
        return None
    i = int(idx[0])
    return float(s[i] + (z[i] - level) / (z[i] - z[i + 1]) * (s[i + 1] - s[i]))


def _refine(scope: _Scope, ring: np.ndarray, i: int, j: int, ps: float) -> _Side | None:
    """The side from vertex ``i`` to ``j`` moved onto the half-height line it images as."""
    a, b = ring[i], ring[j]
    length = math.hypot(*(b - a))
    u = (b - a) / length
    n = np.array([u[1], -u[0]])                       # outward for a CCW ring
    margin = max(3 * ps, 30.0)                        # clear of the rounded corners
    t = np.arange(margin, length - margin + 1e-9, ps)
    if len(t) < 3:
        return None
    c, _, _ = scope.crossings(a + t[:, None] * u, n)
    good = np.isfinite(c)
    if good.sum() < 3:
        return None
    tg, cg = t[good], c[good]
    keep = np.ones(len(tg), bool)
    for _ in range(3):                                # a line robust to a few bad profiles
        slope, icpt = np.polyfit(tg[keep], cg[keep], 1)
        r = cg - (icpt + slope * tg)
        keep = np.abs(r) <= max(3 * _robust_std(r[keep]), 0.1 * ps)
        if keep.sum() < 3:
            return None
    turn = math.atan(slope)
    u2 = math.cos(turn) * u + math.sin(turn) * n
    n2 = np.array([u2[1], -u2[0]])
    q = a + icpt * n
    return _Side(q, u2, n2, float(np.dot(b - q, u2)))


def _site(scope: _Scope, side: _Side, t: float, height: float, ps: float) -> EdgeSite | None:
    """The crossing of ``side`` at ``t`` read from :data:`BAND` profiles, or None when they
    disagree, the step is not the obstacle's, or the band leaves the image."""
    k = np.arange(BAND) - (BAND - 1) / 2
    starts = side.q + (t + k[:, None] * ps) * side.u
    c, pts, steps = scope.crossings(starts, side.n)
    good = np.isfinite(c)
    if good.sum() < BAND:
        return None
    mid = float(np.median(c))
    if np.max(np.abs(c - mid)) > MAX_STRAY * ps:
        return None
    step = float(np.median(steps))
    if not abs(step - height) <= HEIGHT_TOLERANCE * height:
        return None
    std = math.hypot(float(np.std(c, ddof=1)) / math.sqrt(BAND), PIXEL_FLOOR * ps)
    p = side.q + t * side.u + mid * side.n
    row = float(np.mean((pts[:, 1] - scope.image.origin[1]) / ps - 0.5))
    return EdgeSite((float(p[0]), float(p[1])), (float(side.n[0]), float(side.n[1])), step, std, row)


def _scope(image: HeightImage, poly: shapely.Polygon, others: shapely.Geometry) -> _Scope:
    ps = image.pixel_size
    gap = max(LEVEL_GAP[0] * ps, LEVEL_GAP[1])
    far = gap + max(LEVEL_WIDTH[0] * ps, LEVEL_WIDTH[1])
    s = np.arange(-far, far + 1e-9, PROFILE_STEP * ps)
    inside = poly.buffer(-ps)
    outside = shapely.union(others, poly).buffer(ps)
    shapely.prepare(inside)
    shapely.prepare(outside)
    return _Scope(image, s, gap, inside, outside)


# ---------------------------------------------------------------- features

def find_features(image: HeightImage, obstacles: Sequence, *, min_edge: float | None = None,
                  corner_distance: float | None = None, corner_angles: tuple[float, float] = (45.0, 135.0),
                  corner_gap: float | None = None) -> tuple[Feature, ...]:
    """Edge and corner features of the obstacles' straight sides, refined in ``image``.

    Each obstacle polygon (as identification outlines it) is split into straight sides
    (runs of vertices within a pixel of their chord). A side counts if it is at least
    ``min_edge`` long and does not lie along the image border (where the obstacle is
    cut). It is moved onto the half-height line it images as (crossings of profiles a
    pixel apart along it, a robust straight-line fit), and sites on it are read from
    :data:`BAND` profiles a pixel apart, each crossing between the median top and
    substrate levels taken :data:`LEVEL_GAP` beyond the step (so a tilt cancels), with
    bilinear interpolation. A site is dropped when its profiles disagree by more than
    :data:`MAX_STRAY` pixel (something on the edge), its step differs from the obstacle's
    height by more than :data:`HEIGHT_TOLERANCE`, or its profiles leave the image.

    An edge feature has sites at a quarter and three quarters of the side (at least
    ``corner_distance`` from its ends). A corner feature is made where two counted
    sides meet, through at most ``corner_gap`` of the outline (the rounding the tip and
    the pixels give), with an interior angle within ``corner_angles``: one site on each
    side, ``corner_distance`` from where their half-height lines cross.

    Parameters
    ----------
    image : HeightImage
        The full scan the obstacles were identified in (their frame is the image's).
    obstacles : sequence
        Each with ``.polygon`` (vertices, or a shapely Polygon) and ``.height`` (nm), such
        as :class:`~nanoasm.world.environment.EnvObstacle`.
    min_edge : float, optional
        Shortest side used (nm); ``max(12 px, 120 nm)`` by default.
    corner_distance : float, optional
        Distance of sites from a corner (nm); ``max(5 px, 50 nm)`` by default. It must
        exceed the corner's rounding plus the drift the local lines may still miss
        along the edge.
    corner_angles : (lo, hi)
        Interior angles (degrees) of a sharp corner.
    corner_gap : float, optional
        Longest outline between two sides meeting at a corner (nm); ``max(5 px, 50 nm)``.

    Returns
    -------
    tuple of Feature
        In obstacle and vertex order; ids ``"e1", "e2", ...`` and ``"c1", ...``.
    """
    if not isinstance(image, HeightImage):
        raise ValueError(f"image must be a HeightImage, got {type(image).__name__}")
    ps = image.pixel_size
    min_edge = max(12 * ps, 120.0) if min_edge is None else number("min_edge", min_edge, positive=True)
    dist = (max(5 * ps, 50.0) if corner_distance is None
            else number("corner_distance", corner_distance, positive=True))
    gap = max(5 * ps, 50.0) if corner_gap is None else number("corner_gap", corner_gap, nonnegative=True)
    lo, hi = (number("corner_angles", a, lo=0.0, hi=180.0) for a in corner_angles)
    polys, heights = _obstacle_list(obstacles)
    features: list[Feature] = []
    counts = {"edge": 0, "corner": 0}

    def add(kind: str, k: int, sites: list) -> None:
        if len(sites) == 2 and all(s is not None for s in sites):
            counts[kind] += 1
            features.append(Feature(f"{kind[0]}{counts[kind]}", kind, k, tuple(sites)))

    for k, (poly, height) in enumerate(zip(polys, heights)):
        others = shapely.union_all([p for m, p in enumerate(polys) if m != k])
        scope = _scope(image, poly, others)
        ring = _ring(poly)
        runs = _straight_runs(ring, ps)
        sides = [_counted(scope, ring, i, j, image, min_edge) for i, j in runs]
        for r, side in enumerate(sides):
            if side is None:
                continue
            s = max(dist, side.length / 4)
            if side.length - 2 * s >= BAND * ps:
                add("edge", k, [_site(scope, side, t, height, ps) for t in (s, side.length - s)])
            nxt, path = _next_side(sides, runs, ring, r)
            if nxt is not None and path <= gap:
                corner = _corner(side, nxt, lo, hi)
                if corner is not None:
                    t1 = float(np.dot(corner - side.q, side.u)) - dist
                    t2 = float(np.dot(corner - nxt.q, nxt.u)) + dist
                    add("corner", k, [_site(scope, side, t1, height, ps),
                                      _site(scope, nxt, t2, height, ps)])
    return tuple(features)


def _obstacle_list(obstacles) -> tuple[list[shapely.Polygon], list[float]]:
    polys, heights = [], []
    for i, o in enumerate(obstacles):
        poly = o.polygon if isinstance(o.polygon, shapely.Polygon) else shapely.Polygon(list(o.polygon))
        if not (poly.is_valid and poly.area > 0):
            raise ValueError(f"obstacles[{i}]: polygon must be valid with a positive area")
        polys.append(poly)
        heights.append(number(f"obstacles[{i}].height", o.height, positive=True))
    return polys, heights


def _counted(scope: _Scope, ring: np.ndarray, i: int, j: int, image: HeightImage,
             min_edge: float) -> _Side | None:
    a, b = ring[i], ring[j]
    if math.hypot(*(b - a)) < min_edge or _on_border(a, b, image):
        return None
    return _refine(scope, ring, i, j, image.pixel_size)


def _next_side(sides: list, runs: list, ring: np.ndarray, r: int) -> tuple[_Side | None, float]:
    """The side after side ``r`` round the ring and the outline length between them,
    if only short (uncounted) runs lie between them."""
    n_runs = len(runs)
    path = 0.0
    for step in range(1, n_runs):
        k = (r + step) % n_runs
        if sides[k] is not None:
            return sides[k], path
        i, j = runs[k]
        path += math.hypot(*(ring[j] - ring[i]))
    return None, path


def _corner(s1: _Side, s2: _Side, lo: float, hi: float) -> np.ndarray | None:
    """Where the half-height lines of two consecutive sides cross, if they make a convex
    corner with an interior angle in [lo, hi] degrees."""
    cross = s1.u[0] * s2.u[1] - s1.u[1] * s2.u[0]
    turn = math.degrees(math.atan2(cross, float(np.dot(s1.u, s2.u))))
    if not (turn > 0 and lo <= 180.0 - turn <= hi):
        return None
    # s1.q + a s1.u = s2.q + b s2.u
    a = ((s2.q - s1.q)[0] * s2.u[1] - (s2.q - s1.q)[1] * s2.u[0]) / cross
    return s1.q + a * s1.u


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
    a step whose height is off by more than :data:`HEIGHT_TOLERANCE`, more crossings of
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
    """

    found: bool
    offsets: np.ndarray
    stds: np.ndarray
    ok: np.ndarray
    reason: str
    lines: int
    samples: int
    steps: tuple[StepCrossing, ...] = ()


def edge_pattern(sites_scanner: Sequence, reach: float, *, spacing: float = 1.0,
                 height: float | None = None, site_stds=None
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
    return _edge_lines(sites, reach, spacing, height, extra)


def _scanner_site(k: int, site) -> tuple[np.ndarray, np.ndarray, float]:
    try:
        p, n, h = site
    except (TypeError, ValueError):
        raise ValueError(f"sites_scanner[{k}] must be (point, normal, height), got {site!r}") from None
    return (point(f"sites_scanner[{k}] point", p), unit(f"sites_scanner[{k}] normal", n),
            number(f"sites_scanner[{k}] height", h, positive=True))


def _edge_lines(sites, reach, spacing, height, extra):
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
    if reason == "found":
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
