"""Corners of outlines: where two straight edges meet, for registering marks to obstacles.

A layout's mark is an exact polygon; the obstacle identification found where that mark
lies is the outline of its pixels above the cut plane: a staircase simplified to half a
pixel, grown by the tip's broadening, its convex corners rounded. Both give the same
corners when a corner is taken as the intersection of the lines of two long straight
edges rather than as a vertex: edges keep their direction under growth and rounding,
and the rounded corner's edges still meet where the grown (mitred) outline's corner is.

So a :class:`Corner` is that intersection, with its ``turn`` (degrees, positive at a
convex corner, negative at a concave one) and its ``miter``: how far the corner moves
per nm the outline grows, ``(n1 + n2) / (1 + n1 . n2)`` for the outward normals of its
edges. A registration fits that growth as one unknown (:mod:`.alignment`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry.polygon import orient

from nanoasm.schema import Point

#: Segments within this many degrees of a straight run's direction belong to it.
STRAIGHT = 15.0
#: Segments at a run's ends more than this many degrees off its direction (a rounded
#: corner's) are left out of its line.
TRUE_LINE = 4.0
#: Least turn (degrees) between two edges for a corner, and most (beyond it the two
#: edges are nearly antiparallel: a spike, whose corner the growth moves too far).
MIN_TURN, MAX_TURN = 30.0, 150.0


@dataclass(frozen=True)
class Corner:
    """Where two straight edges of outline ``outline`` meet (nm), the turn between them
    (degrees, + convex) and the corner's shift per nm of outward growth."""

    at: Point
    turn: float
    miter: Point
    outline: int


def _wrap(a: float) -> float:
    """An angle in degrees wrapped into [-180, 180)."""
    return (a + 180.0) % 360.0 - 180.0


def _ring(points) -> np.ndarray:
    """The counter-clockwise ring of a polygon's vertices, without the closing repeat."""
    poly = shapely.Polygon(points)
    if not poly.is_valid or poly.area <= 0:
        poly = shapely.make_valid(poly)
        parts = [p for p in getattr(poly, "geoms", [poly]) if isinstance(p, shapely.Polygon)]
        if not parts:
            return np.zeros((0, 2))
        poly = max(parts, key=lambda p: p.area)
    return np.asarray(orient(poly, 1.0).exterior.coords)[:-1]


def _runs(ring: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, float, int, int]]:
    """Straight runs of the ring's segments: (direction, point on the line, length, first
    segment, last segment), cyclic, starting after the sharpest turn."""
    n = len(ring)
    seg = np.roll(ring, -1, axis=0) - ring
    length = np.hypot(seg[:, 0], seg[:, 1])
    keep = length > 1e-6 * max(1.0, float(np.abs(ring).max()))      # no direction below a micro-nm
    if keep.sum() < 3:
        return []
    theta = np.degrees(np.arctan2(seg[:, 1], seg[:, 0]))
    turns = np.array([abs(_wrap(theta[i] - theta[i - 1])) for i in range(n)])
    start = int(np.argmax(np.where(keep, turns, -1.0)))
    runs: list[list[int]] = []
    for k in range(n):
        i = (start + k) % n
        if not keep[i]:
            continue
        if runs:
            cur = runs[-1]
            u = seg[cur].sum(axis=0)            # the run's length-weighted direction
            if abs(_wrap(theta[i] - math.degrees(math.atan2(u[1], u[0])))) < STRAIGHT:
                cur.append(i)
                continue
        runs.append([i])
    out = []
    for idx in runs:
        total = float(length[idx].sum())
        use = list(idx)
        # the segments of a rounded corner that joined the run at either end bend its
        # line: leave them out while they are off its direction by more than TRUE_LINE
        # and most of its length stays
        while len(use) > 1:
            u = seg[use].sum(axis=0)
            ang = math.degrees(math.atan2(u[1], u[0]))
            end = max((0, len(use) - 1), key=lambda e: abs(_wrap(theta[use[e]] - ang)))
            if abs(_wrap(theta[use[end]] - ang)) <= TRUE_LINE or length[use].sum() - length[use[end]] < total / 2:
                break
            use.pop(end)
        u = seg[use].sum(axis=0)
        u /= np.hypot(*u)
        mid = ((ring[use] + seg[use] / 2) * length[use, None]).sum(axis=0) / length[use].sum()
        out.append((u, mid, total, idx[0], idx[-1]))
    return out


def _fitted(run, ring: np.ndarray, dense: np.ndarray, tolerance: float):
    """``run`` with its line fitted (total least squares) to the points of the outline
    ``dense`` along its middle (a fifth of it left out at either end: the corners' rounding)
    within ``2 tolerance`` of it; as it was when fewer than 3 are."""
    u, mid, total, first, last = run
    start = ring[first]
    rel = dense - start
    along, off = rel @ u, rel @ np.array([-u[1], u[0]])
    length = float((ring[(last + 1) % len(ring)] - start) @ u)
    pick = (along >= 0.2 * length) & (along <= 0.8 * length) & (np.abs(off) <= 2 * tolerance)
    if pick.sum() < 3:
        return run
    pts = dense[pick]
    c = pts.mean(axis=0)
    w, v = np.linalg.eigh(np.cov((pts - c).T))
    d = v[:, int(np.argmax(w))]
    return (d if d @ u >= 0 else -d), c, total, first, last


def corners(points, *, min_edge: float, max_gap: float, tolerance: float = 0.0, outline: int = 0) -> list[Corner]:
    """The corners of the polygon with vertices ``points`` (nm): consecutive straight
    edges at least ``min_edge`` long that turn by ``MIN_TURN`` to ``MAX_TURN`` degrees
    and whose lines meet within ``max_gap`` of where each edge ends.

    ``tolerance`` (nm, about a pixel): how far an outline traced from an image strays
    from its straight edges (a staircase). The outline is simplified to it to find the
    edges, and each edge's line is fitted to the outline's points along it."""
    ring = _ring(points)
    if len(ring) < 3:
        return []
    if tolerance > 0:
        poly = shapely.Polygon(ring)
        dense = np.asarray(shapely.segmentize(poly, tolerance / 2).exterior.coords)[:-1]
        ring = _ring(poly.simplify(tolerance, preserve_topology=True).exterior.coords)
        if len(ring) < 3:
            return []
    edges = [r for r in _runs(ring) if r[2] >= min_edge]
    if tolerance > 0:
        edges = [_fitted(r, ring, dense, tolerance) for r in edges]
    out: list[Corner] = []
    n = len(ring)
    for a, b in zip(edges, edges[1:] + edges[:1]):
        if a is b:
            break
        (ua, pa, _, _, last), (ub, pb, _, first, _) = a, b
        turn = _wrap(math.degrees(math.atan2(ub[1], ub[0]) - math.atan2(ua[1], ua[0])))
        if not MIN_TURN <= abs(turn) <= MAX_TURN:
            continue
        det = ua[0] * (-ub[1]) - ua[1] * (-ub[0])
        if abs(det) < 1e-9:
            continue
        d = pb - pa
        s = (d[0] * (-ub[1]) - d[1] * (-ub[0])) / det
        at = pa + s * ua
        end_a, start_b = ring[(last + 1) % n], ring[first]
        if np.hypot(*(at - end_a)) > max_gap or np.hypot(*(at - start_b)) > max_gap:
            continue
        na, nb = np.array([ua[1], -ua[0]]), np.array([ub[1], -ub[0]])
        miter = (na + nb) / (1.0 + float(na @ nb))
        out.append(Corner((float(at[0]), float(at[1])), float(turn), (float(miter[0]), float(miter[1])), outline))
    return out
