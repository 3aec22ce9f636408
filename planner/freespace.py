"""Free space for pushing: what a moving footprint must keep clear of.

Everything in the way is a *core* geometry (a polygon, a point or a segment) with a
radius: keep-outs and obstacles are polygons of radius 0, objects are the cores of their
footprints. A footprint of core ``g`` and radius ``r`` is free when for every entry
``distance(g, core) >= r + radius + clearance``. Fixed things sit in one STRtree built
once; movable objects in a second one rebuilt lazily after moves.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

import numpy as np
import shapely

from nanoasm.bodies import Body


class FreeSpace:
    """Clearance queries against fixed geometry and movable bodies in an area.

    Parameters
    ----------
    area : (w, h)
        Footprints must stay inside ``[0, w] x [0, h]``.
    fixed : sequence of (geometry, radius)
        Keep-outs, obstacles, and objects that are never moved (wires, edge objects).
    bodies : mapping id -> Body
        Movable objects at their current positions.
    clearance : float
        Gap, nm, kept beyond the footprints (tip radius + margin).
    """

    def __init__(self, area: tuple[float, float], fixed: Sequence[tuple[shapely.Geometry, float]],
                 bodies: Mapping[str, Body], clearance: float):
        self.area = area
        self.clearance = float(clearance)
        self._fixed = np.array([g for g, _ in fixed], dtype=object)
        self._fixed_r = np.array([r for _, r in fixed], dtype=float)
        self._fixed_tree = shapely.STRtree(self._fixed) if len(fixed) else None
        self._fixed_rmax = float(self._fixed_r.max()) if len(fixed) else 0.0
        self.bodies: dict[str, Body] = dict(bodies)
        self._dirty = True              # every core to make anew
        self._moved = False             # some cores replaced: the tree to build anew
        self._slot: dict[str, int] = {}

    # -- movable bodies ---------------------------------------------------------------
    def move(self, body: Body) -> None:
        """Put ``body`` (by id) at its new pose: its core alone is made anew (the tree is
        rebuilt at the next query, in one call), so a plan of many pushes among many
        objects does not remake every object's geometry after each push."""
        self.bodies[body.id] = body
        k = self._slot.get(body.id)
        if self._dirty or k is None:
            self._dirty = True
            return
        self._cores[k] = body.geometry()
        self._radii[k] = body.radius
        self._moved = True

    def _index(self) -> None:
        if self._dirty:
            self._ids = list(self.bodies)
            self._slot = {i: k for k, i in enumerate(self._ids)}
            self._cores = np.array([self.bodies[i].geometry() for i in self._ids], dtype=object)
            self._radii = np.array([self.bodies[i].radius for i in self._ids], dtype=float)
        elif not self._moved:
            return
        self._tree = shapely.STRtree(self._cores) if self._ids else None
        self._rmax = float(self._radii.max()) if self._ids else 0.0
        self._dirty = self._moved = False

    # -- queries ----------------------------------------------------------------------
    def inside(self, geom: shapely.Geometry, radius: float) -> bool:
        return self.inside_box(*geom.bounds, radius)

    def inside_box(self, x0: float, y0: float, x1: float, y1: float, radius: float) -> bool:
        """Whether a footprint whose core has bounds (x0, y0, x1, y1) lies in the area."""
        return x0 >= radius and y0 >= radius and x1 <= self.area[0] - radius and y1 <= self.area[1] - radius

    def _hits(self, geom, radius, tree, cores, radii, rmax, clearance) -> np.ndarray:
        if tree is None:
            return np.empty(0, dtype=int)
        reach = radius + (self.clearance if clearance is None else clearance)
        idx = tree.query(geom, predicate="dwithin", distance=reach + rmax)
        if idx.size == 0:
            return idx
        d = shapely.distance(geom, cores[idx])
        return idx[d < reach + radii[idx] - 1e-9]

    def fixed_hits(self, geom: shapely.Geometry, radius: float, clearance: float | None = None) -> np.ndarray:
        """Indices of fixed entries within reach of the footprint (geom, radius).

        ``clearance`` overrides the space's own (0: contact only)."""
        return self._hits(geom, radius, self._fixed_tree, self._fixed, self._fixed_r, self._fixed_rmax,
                          clearance)

    def lying_on(self, geom: shapely.Geometry, radius: float) -> frozenset[int]:
        """Fixed entries a footprint already touches (an object found on a keep-out may be
        pushed off it: checks exempt these)."""
        return frozenset(self.fixed_hits(geom, radius, 0.0).tolist())

    def blockers(self, geom: shapely.Geometry, radius: float, ignore: Iterable[str] = (),
                 clearance: float | None = None) -> list[str]:
        """Ids of movable bodies within reach of the footprint, sorted."""
        self._index()
        idx = self._hits(geom, radius, self._tree, self._cores, self._radii, self._rmax, clearance)
        skip = set(ignore)
        return sorted(self._ids[i] for i in idx if self._ids[i] not in skip)

    def _any_hit(self, geoms: np.ndarray, radius: float, tree, cores, radii, rmax, clearance,
                 skip) -> bool:
        if tree is None:
            return False
        reach = radius + (self.clearance if clearance is None else clearance)
        gi, ci = tree.query(geoms, predicate="dwithin", distance=reach + rmax)
        if gi.size == 0:
            return False
        d = shapely.distance(geoms[gi], cores[ci])
        near = ci[d < reach + radii[ci] - 1e-9]
        return bool(near.size) and not set(near.tolist()) <= skip

    def all_free(self, geoms: np.ndarray, radius: float, ignore: Iterable[str] = (),
                 exempt_fixed: frozenset[int] = frozenset(), clearance: float | None = None) -> bool:
        """:meth:`is_free` for every footprint of ``geoms`` (an array of cores sharing
        ``radius``) in two tree queries: True when all are clear."""
        geoms = np.asarray(geoms, dtype=object)
        if geoms.size == 0:
            return True
        x0, y0, x1, y1 = shapely.bounds(geoms).T
        w, h = self.area
        if not ((x0 >= radius).all() and (y0 >= radius).all() and (x1 <= w - radius).all()
                and (y1 <= h - radius).all()):
            return False
        if self._any_hit(geoms, radius, self._fixed_tree, self._fixed, self._fixed_r, self._fixed_rmax,
                         clearance, set(exempt_fixed)):
            return False
        self._index()
        skip = {self._slot[i] for i in set(ignore) if i in self._slot}
        return not self._any_hit(geoms, radius, self._tree, self._cores, self._radii, self._rmax,
                                 clearance, skip)

    def is_free(self, geom: shapely.Geometry, radius: float, ignore: Iterable[str] = (),
                exempt_fixed: frozenset[int] = frozenset(), clearance: float | None = None) -> bool:
        """True when the footprint (or the area it sweeps, for a segment) is clear by
        ``clearance`` (default: the space's own; 0: no contact).

        ``exempt_fixed``: fixed entries not to count (ones an object already lies on).
        """
        if not self.inside(geom, radius):
            return False
        hits = self.fixed_hits(geom, radius, clearance)
        if hits.size and not set(hits.tolist()) <= exempt_fixed:
            return False
        return not self.blockers(geom, radius, ignore, clearance)

    def slack(self, geom: shapely.Geometry, radius: float, ignore: Iterable[str] = (),
              horizon: float = 1e3) -> float:
        """Smallest spare distance to anything (negative inside), capped at ``horizon``."""
        self._index()
        x0, y0, x1, y1 = geom.bounds
        best = min(x0, y0, self.area[0] - x1, self.area[1] - y1) - radius
        reach = radius + self.clearance
        skip = set(ignore)
        for tree, cores, radii, rmax, ids in (
                (self._fixed_tree, self._fixed, self._fixed_r, self._fixed_rmax, None),
                (self._tree, getattr(self, "_cores", None), getattr(self, "_radii", None), self._rmax,
                 getattr(self, "_ids", None))):
            if tree is None:
                continue
            idx = tree.query(geom, predicate="dwithin", distance=reach + rmax + horizon)
            if ids is not None:
                idx = np.array([i for i in idx if ids[i] not in skip], dtype=int)
            if idx.size:
                d = shapely.distance(geom, cores[idx]) - radii[idx] - reach
                best = min(best, float(d.min()))
        return min(best, horizon)
