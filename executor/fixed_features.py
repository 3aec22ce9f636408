"""Fixed features for drift: straight obstacle edges and sharp corners in the full scan.

Electrodes and pads never move, so where their straight edges lie measures the drift
after every object has been pushed (Li, Wang and Liu, IEEE T-ASE 2012: local scans of
one fixed feature). A straight edge measures one coordinate, the one along its normal;
a sharp corner, through one site on each of its two edges, measures both. An
:class:`EdgeSite` is where the half-height crossing of a step lies, a :class:`Feature`
an edge's or a corner's sites, and :func:`find_features` reads them off the full scan to
sub-pixel precision; the local lines that find them again are in
:mod:`~nanoasm.executor.edge_scan`. Lengths in nm; ``row`` is an image row index (row 0
at the bottom, scanned first).

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
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import shapely
from scipy import ndimage
from shapely.geometry.polygon import orient

from nanoasm.instrument import HeightImage
from nanoasm.param import number

from .substrate import _robust_std
from .feature_types import EdgeSite, Feature
from .scan_lines import perp, wedge

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
#: A step differing from the obstacle's height by more than this fraction is refused
#: (in the full scan here and on a local line by :func:`~nanoasm.executor.edge_scan.locate_step`).
HEIGHT_TOLERANCE = 0.3
#: Pixel-phase error of a full-scan crossing (pixels, 1-sigma; see the module docstring).
PIXEL_FLOOR = 0.08
#: How far (nm) from a corner its rounding (the tip's and the pixels') may reach along an edge.
CORNER_ROUNDING = 15.0


# ---------------------------------------------------------------- polygon sides

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
    """Whether the vertices between ``i`` and ``j`` lie within ``tol`` of their chord."""
    n = len(ring)
    a, d = ring[i % n], ring[j % n] - ring[i % n]
    mid = ring[[k % n for k in range(i + 1, j)]].reshape(-1, 2)
    return bool(np.any(d) and np.all(np.abs((mid - a) @ perp(d)) <= tol * math.hypot(*d)))


def _on_border(a: np.ndarray, b: np.ndarray, image: HeightImage) -> bool:
    """Whether the side from ``a`` to ``b`` runs along the image's border (within a pixel)."""
    lo = np.asarray(image.origin, float)
    near = [(np.abs(a - e) <= image.pixel_size) & (np.abs(b - e) <= image.pixel_size)
            for e in (lo, lo + np.asarray(image.extent, float))]
    return bool(np.any(near))


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
        c, steps = np.full(len(starts), np.nan), np.full(len(starts), np.nan)
        for i in range(len(starts)):
            if top[i].sum() < 3 or low[i].sum() < 3 or not valid[i, ~far].all():
                continue
            hi, lo = np.median(z[i, top[i]]), np.median(z[i, low[i]])
            ci = _down_crossing(z[i], self.s, lo + 0.5 * (hi - lo), ~far)
            if ci is not None:
                c[i], steps[i] = ci, hi - lo
        return c, starts + c[:, None] * n, steps


def _bilinear(image: HeightImage, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Heights at points ``(..., 2)`` (nm) between pixel centres, and where they are inside."""
    cols, rows = np.moveaxis((pts - np.asarray(image.origin)) / image.pixel_size - 0.5, -1, 0)
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


def _refine(scope: _Scope, a: np.ndarray, b: np.ndarray, min_edge: float) -> _Side | None:
    """The side from ``a`` to ``b`` moved onto the half-height line it images as; None
    when it is shorter than ``min_edge``, lies along the image border, or images badly."""
    length = math.hypot(*(b - a))
    if length < min_edge or _on_border(a, b, scope.image):
        return None
    ps = scope.image.pixel_size
    u = (b - a) / length
    n = np.array([u[1], -u[0]])                       # outward for a CCW ring
    margin = max(3 * ps, 30.0)                        # clear of the rounded corners
    t = np.arange(margin, length - margin + 1e-9, ps)
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


def _site(scope: _Scope, side: _Side, t: float, height: float, ps: float, room: float) -> EdgeSite | None:
    """The crossing of ``side`` at ``t`` read from :data:`BAND` profiles, or None when they
    disagree, the step is not the obstacle's, or the band leaves the image."""
    k = np.arange(BAND) - (BAND - 1) / 2
    starts = side.q + (t + k[:, None] * ps) * side.u
    c, pts, steps = scope.crossings(starts, side.n)
    if not np.isfinite(c).all():
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
    return EdgeSite((float(p[0]), float(p[1])), (float(side.n[0]), float(side.n[1])), step, std, row,
                    max(room, 0.0))


def _scope(image: HeightImage, poly: shapely.Polygon, others: shapely.Geometry) -> _Scope:
    ps = image.pixel_size
    gap = max(LEVEL_GAP[0] * ps, LEVEL_GAP[1])
    far = gap + max(LEVEL_WIDTH[0] * ps, LEVEL_WIDTH[1])
    s = np.arange(-far, far + 1e-9, PROFILE_STEP * ps)
    inside, outside = poly.buffer(-ps), shapely.union(others, poly).buffer(ps)
    shapely.prepare([inside, outside])
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
        ring = np.asarray(orient(poly).exterior.coords, float)[:-1]     # CCW, vertex 0 first
        runs = _straight_runs(ring, ps)
        sides = [_refine(scope, ring[i], ring[j], min_edge) for i, j in runs]
        for r, side in enumerate(sides):
            if side is None:
                continue
            s = max(dist, side.length / 4)
            if side.length - 2 * s >= BAND * ps:
                add("edge", k, [_site(scope, side, t, height, ps, s - BAND * ps / 2) for t in (s, side.length - s)])
            nxt, path = _next_side(sides, runs, ring, r)
            corner = None if nxt is None or path > gap else _corner(side, nxt, lo, hi)
            if corner is not None:
                t1 = float(np.dot(corner - side.q, side.u)) - dist
                t2 = float(np.dot(corner - nxt.q, nxt.u)) + dist
                room = dist - max(CORNER_ROUNDING, 1.5 * ps)
                add("corner", k, [_site(scope, side, t1, height, ps, room), _site(scope, nxt, t2, height, ps, room)])
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


def _next_side(sides: list, runs: list, ring: np.ndarray, r: int) -> tuple[_Side | None, float]:
    """The side after side ``r`` round the ring and the outline length between them,
    if only short (uncounted) runs lie between them."""
    path = 0.0
    for k in range(r + 1, r + len(runs)):
        k %= len(runs)
        if sides[k] is not None:
            return sides[k], path
        i, j = runs[k]
        path += math.hypot(*(ring[j] - ring[i]))
    return None, path


def _corner(s1: _Side, s2: _Side, lo: float, hi: float) -> np.ndarray | None:
    """Where the half-height lines of two consecutive sides cross, if they make a convex
    corner with an interior angle in [lo, hi] degrees."""
    cross = wedge(s1.u, s2.u)
    turn = math.degrees(math.atan2(cross, float(np.dot(s1.u, s2.u))))
    if not (turn > 0 and lo <= 180.0 - turn <= hi):
        return None
    return s1.q + wedge(s2.q - s1.q, s2.u) / cross * s1.u      # s1.q + a s1.u = s2.q + b s2.u
