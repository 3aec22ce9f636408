"""Free space for pushing: what a moving footprint must keep clear of.

Everything in the way is a *core* geometry (a polygon, a point or a segment) with a
radius: keep-outs and obstacles are polygons of radius 0, objects are the cores of their
footprints. A footprint of core ``g`` and radius ``r`` is free when for every entry
``distance(g, core) >= r + radius + clearance``. Fixed things sit in one STRtree built
once; movable objects in an array of their cores' bounding boxes, which a move updates
in place (an STRtree rebuilt after every planned push cost a plan O(N log N) a push):
a query's candidates are the boxes within reach of its own, one vectorised comparison,
and the same exact distances decide as before.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

import numpy as np
import shapely

from nanoasm.bodies import Body, geometries


#: How much (nm) wider than a query's reach the movable boxes it takes are: float rounding.
BOX_SLACK = 1e-6


def _all_inside(geoms: np.ndarray, radius: float, area: tuple[float, float]) -> bool:
    """Every footprint (core, radius) lies in ``[0, w] x [0, h]``."""
    x0, y0, x1, y1 = shapely.bounds(geoms).T
    w, h = area
    return bool((x0 >= radius).all() and (y0 >= radius).all() and (x1 <= w - radius).all()
                and (y1 <= h - radius).all())


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
        self._slot: dict[str, int] = {}

    # -- movable bodies ---------------------------------------------------------------
    def move(self, body: Body) -> None:
        """Put ``body`` (by id) at its new pose: its core and box alone are made anew, so
        a plan of many pushes among many objects does not remake every object's geometry
        (or an index of them) after each push."""
        self.bodies[body.id] = body
        k = self._slot.get(body.id)
        if self._dirty or k is None:
            self._dirty = True
            return
        self._cores[k] = core = body.geometry()
        self._radii[k] = body.radius
        self._boxes[k] = shapely.bounds(core)
        self._rmax = max(self._rmax, float(body.radius))     # an upper bound: reach only widens

    def _index(self) -> None:
        if not self._dirty:
            return
        self._ids = list(self.bodies)
        self._slot = {i: k for k, i in enumerate(self._ids)}
        self._cores = geometries([self.bodies[i] for i in self._ids])
        self._radii = np.array([self.bodies[i].radius for i in self._ids], dtype=float)
        self._boxes = shapely.bounds(self._cores).reshape(-1, 4)
        self._rmax = float(self._radii.max()) if self._ids else 0.0
        self._dirty = False

    def _boxed(self, boxes, reach: float) -> tuple[np.ndarray, np.ndarray]:
        """Pairs (box, slot) of ``boxes`` ``(m, 4)`` and the movable cores whose boxes come
        within ``reach`` of them (a hair more): every core within ``reach`` of a geometry
        inside a box is paired with it."""
        g, b, m = np.asarray(boxes, float).reshape(-1, 4), self._boxes, reach + BOX_SLACK
        return np.nonzero((b[None, :, 0] <= g[:, 2, None] + m) & (b[None, :, 2] >= g[:, 0, None] - m)
                          & (b[None, :, 1] <= g[:, 3, None] + m) & (b[None, :, 3] >= g[:, 1, None] - m))

    def _movable_hits(self, geoms: np.ndarray, radius: float, clearance: float | None) -> np.ndarray:
        """Slots of the movable cores within reach of any footprint (``geoms``, ``radius``)."""
        reach = radius + (self.clearance if clearance is None else clearance)
        gi, ci = self._boxed(shapely.bounds(geoms), reach + self._rmax)
        return ci[shapely.distance(geoms[gi], self._cores[ci]) < reach + self._radii[ci] - 1e-9]

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

    def fixed_footprint(self, i: int) -> shapely.Geometry:
        """Fixed entry ``i`` as the area it covers (its geometry grown by its radius)."""
        g, r = self._fixed[i], float(self._fixed_r[i])
        return g.buffer(r, quad_segs=16) if r > 0 else g

    def blockers(self, geom: shapely.Geometry, radius: float, ignore: Iterable[str] = (),
                 clearance: float | None = None) -> list[str]:
        """Ids of movable bodies within reach of the footprint, sorted."""
        self._index()
        skip = set(ignore)
        return sorted(self._ids[i] for i in self._movable_hits(np.array([geom]), radius, clearance).tolist()
                      if self._ids[i] not in skip)

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
        if not _all_inside(geoms, radius, self.area):
            return False
        if self._any_hit(geoms, radius, self._fixed_tree, self._fixed, self._fixed_r, self._fixed_rmax,
                         clearance, set(exempt_fixed)):
            return False
        self._index()
        skip = {self._slot[i] for i in set(ignore) if i in self._slot}
        return set(self._movable_hits(geoms, radius, clearance).tolist()) <= skip

    def nearby(self, bounds: tuple[float, float, float, float], radius: float,
               clearance: float | None = None) -> "Nearby":
        """The entries that may come within reach of a footprint of ``radius`` (and
        ``clearance``, default the space's own) whose core lies inside ``bounds``
        (x0, y0, x1, y1): two box queries, after which :meth:`Nearby.all_free` decides as
        :meth:`all_free` does for such footprints, in one distance call a kind."""
        self._index()
        return Nearby(self, bounds, radius, self.clearance if clearance is None else clearance)

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
        fixed = (self._fixed_tree.query(geom, predicate="dwithin", distance=reach + self._fixed_rmax + horizon)
                 if self._fixed_tree is not None else np.empty(0, dtype=int))
        # the movable boxes give a few more than a tree's distance query would, each beyond the horizon
        movable = np.array([i for i in self._boxed([geom.bounds], reach + self._rmax + horizon)[1].tolist()
                            if self._ids[i] not in skip], dtype=int)
        for idx, cores, radii in ((fixed, self._fixed, self._fixed_r), (movable, self._cores, self._radii)):
            if idx.size:
                d = shapely.distance(geom, cores[idx]) - radii[idx] - reach
                best = min(best, float(d.min()))
        return min(best, horizon)


class Nearby:
    """A :class:`FreeSpace`'s entries near a box (:meth:`FreeSpace.nearby`): every entry
    whose core's envelope comes within the footprint's radius, the clearance and the
    largest entry radius of the box. A footprint
    inside the box can only touch these, so testing it against them alone, with the
    same distances and thresholds as :meth:`FreeSpace.all_free`, gives the same answer:
    a search checking many footprints in one place (a rod's push and its sweep) asks the
    trees once instead of twice a footprint."""

    def __init__(self, space: FreeSpace, bounds: tuple[float, float, float, float], radius: float,
                 clearance: float):
        self.area, self.clearance = space.area, space.clearance
        self._radius, self._clear = radius, clearance
        reach = radius + clearance
        x0, y0, x1, y1 = bounds

        def box(m: float) -> shapely.Geometry:
            return shapely.box(x0 - m, y0 - m, x1 + m, y1 + m)

        if space._fixed_tree is not None:
            fi = space._fixed_tree.query(box(reach + space._fixed_rmax))
        else:
            fi = np.empty(0, dtype=int)
        self._f_idx, self._f_cores, self._f_r = fi, space._fixed[fi], space._fixed_r[fi]
        mi = space._boxed([bounds], reach + space._rmax)[1]
        self._m_ids = [space._ids[i] for i in mi]
        self._m_cores = space._cores[mi] if mi.size else np.empty(0, dtype=object)
        self._m_r = space._radii[mi] if mi.size else np.empty(0)

    @staticmethod
    def _hit(geoms, reach, cores, radii, keep) -> bool:
        if not keep.any():
            return False
        d = shapely.distance(geoms[:, None], cores[keep][None, :])
        return bool((d < reach + radii[keep] - 1e-9).any())

    def all_free(self, geoms: np.ndarray, radius: float, ignore: Iterable[str] = (),
                 exempt_fixed: frozenset[int] = frozenset(), clearance: float | None = None,
                 inside: bool = False) -> bool:
        """:meth:`FreeSpace.all_free` for footprints whose cores lie in the box, of a
        radius and clearance at most those it was made for. ``inside``: the caller has
        found every footprint inside the area (:meth:`FreeSpace.inside_box` of their bounds)."""
        clear = self.clearance if clearance is None else clearance
        if radius > self._radius + 1e-12 or clear > self._clear + 1e-12:
            raise ValueError("a footprint beyond the reach this Nearby was made for")
        geoms = np.asarray(geoms, dtype=object)
        if geoms.size == 0:
            return True
        if not inside and not _all_inside(geoms, radius, self.area):
            return False
        reach = radius + clear
        if self._f_idx.size and self._hit(geoms, reach, self._f_cores, self._f_r,
                                          np.array([i not in exempt_fixed for i in self._f_idx.tolist()])):
            return False
        skip = set(ignore)
        return not (self._m_ids and self._hit(geoms, reach, self._m_cores, self._m_r,
                                              np.array([i not in skip for i in self._m_ids])))
