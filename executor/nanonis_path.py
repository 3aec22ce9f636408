"""A streamed tip path as the follow-me moves of a Nanonis controller.

A chunk of DAC samples (scanner frame, nm) becomes a few straight *legs*: the path is
simplified (Douglas-Peucker) to the vertices that keep every sample within ``tol`` nm
of the simplified line, and each straight piece is cut into equal legs of at most
``contact`` nm if it reaches the surface (z <= 0 at one of its ends) or ``lifted`` nm if
not, a length being the larger of the XY and the Z distance (the slew limit's measure).
The signals are read at the end of every leg, so at least that often. Each leg keeps
the chunk samples it stands for. Nothing here sends anything.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class Leg:
    """A straight move from the previous leg's end (or the start) to ``target`` (``(3,)``
    nm), standing for the chunk samples ``first .. stop - 1``."""

    first: int
    stop: int
    target: np.ndarray

    @property
    def samples(self) -> int:
        return self.stop - self.first


def segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance (nm) of each of ``points`` ``(m, d)`` to the segment from ``a`` to ``b``."""
    ab = b - a
    denom = float(ab @ ab)
    t = np.zeros(len(points)) if denom == 0 else np.clip((points - a) @ ab / denom, 0.0, 1.0)
    return np.linalg.norm(points - (a + t[:, None] * ab), axis=1)


def simplify(points: np.ndarray, tol: float) -> np.ndarray:
    """Indices of the vertices Douglas-Peucker keeps: every point lies within ``tol`` of
    the polyline through them; the first and last are always kept."""
    n = len(points)
    keep = np.zeros(n, bool)
    keep[[0, n - 1]] = True
    stack = [(0, n - 1)]
    while stack:
        a, b = stack.pop()
        if b - a < 2:
            continue
        d = segment_distance(points[a + 1:b], points[a], points[b])
        k = int(np.argmax(d))
        if d[k] > tol:
            m = a + 1 + k
            keep[m] = True
            stack += [(a, m), (m, b)]
    return np.flatnonzero(keep)


def legs(start: np.ndarray, path: np.ndarray, tol: float, contact: float, lifted: float) -> list[Leg]:
    """The legs of ``path`` (``(n, 3)`` nm) played from ``start`` (``(3,)`` nm)."""
    pts = np.vstack([np.asarray(start, float).reshape(1, 3), np.asarray(path, float)])
    out: list[Leg] = []
    vertices = simplify(pts, tol)
    for i0, i1 in zip(vertices[:-1], vertices[1:]):
        a, b = pts[i0], pts[i1]
        length = max(math.hypot(*(b[:2] - a[:2])), abs(b[2] - a[2]))
        longest = contact if min(a[2], b[2]) <= 0 else lifted
        pieces = max(1, min(math.ceil(length / longest - 1e-9), int(i1 - i0)))
        cuts = np.rint(np.linspace(i0, i1, pieces + 1)).astype(int)
        for c0, c1 in zip(cuts[:-1], cuts[1:]):
            out.append(Leg(int(c0), int(c1), pts[c1].copy()))
    return out


__all__ = ["Leg", "legs", "segment_distance", "simplify"]
