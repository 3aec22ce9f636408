"""Nano-objects as value types, with their footprints and overlap checks.

A particle's footprint is a disc; a rod's is a capsule (a segment swept by a disc of
the rod's radius; its length includes the rounded ends). Shared by layout targets,
scene objects and identified objects. Lengths in nm, angles in degrees.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import shapely

from .schema import Point, Table

#: Relative slack below which two footprints count as touching, not overlapping.
TOUCH_EPS = 1e-9


def check_at(body_id: str, at) -> None:
    """A body's ``at`` is two finite numbers (``ValueError`` naming ``body_id`` if not)."""
    if len(at) != 2 or not all(math.isfinite(v) for v in at):
        raise ValueError(f"{body_id}: at must be two finite numbers")


@dataclass(frozen=True)
class Body:
    """A particle or rod: ``at`` is its centre, ``angle`` and ``length`` are for rods."""

    id: str
    kind: str
    at: Point
    diameter: float
    angle: float | None = None
    length: float | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.id, str) or not self.id:
            raise ValueError("id must be a non-empty string")
        check_at(self.id, self.at)
        if not (math.isfinite(self.diameter) and self.diameter > 0):
            raise ValueError(f"{self.id}: diameter must be positive and finite")
        if self.elongated:
            if self.angle is None or self.length is None:
                raise ValueError(f"{self.id}: a {self.kind} needs angle and length")
            if not math.isfinite(self.angle):
                raise ValueError(f"{self.id}: angle must be finite")
            if not (math.isfinite(self.length) and self.length >= self.diameter):
                raise ValueError(f"{self.id}: length must be finite and at least the diameter")
        elif self.angle is not None or self.length is not None:
            raise ValueError(f"{self.id}: a {self.kind} has no angle or length")

    @property
    def elongated(self) -> bool:
        return self.kind in ("rod", "wire")

    @property
    def radius(self) -> float:
        return self.diameter / 2

    @property
    def aspect(self) -> float:
        """Aspect ratio σ = L/d (1 for a particle)."""
        return self.length / self.diameter if self.elongated else 1.0

    def core(self) -> tuple[Point, Point]:
        """End points of the footprint's core segment (equal for a particle)."""
        if not self.elongated:
            return self.at, self.at
        h = (self.length - self.diameter) / 2
        c, s = math.cos(math.radians(self.angle)), math.sin(math.radians(self.angle))
        x, y = self.at
        return (x - h * c, y - h * s), (x + h * c, y + h * s)

    def geometry(self) -> shapely.Geometry:
        """The core as a shapely Point or LineString (buffer by ``radius`` for the footprint)."""
        a, b = self.core()
        return shapely.Point(a) if a == b else shapely.LineString([a, b])

    def bounds(self) -> tuple[float, float, float, float]:
        (x0, y0), (x1, y1) = self.core()
        r = self.radius
        return min(x0, x1) - r, min(y0, y1) - r, max(x0, x1) + r, max(y0, y1) + r

    def to_dict(self) -> dict:
        d: dict = {"id": self.id, "kind": self.kind, "at": list(self.at)}
        if self.elongated:
            d["angle"] = self.angle
            d["length"] = self.length
        d["diameter"] = self.diameter
        return d


def body_from_table(t: Table, default_id: str, kinds: Sequence[str], extra: Sequence[str] = ()) -> tuple[Body, set[str]]:
    """Read one ``[[target]]``/``[[object]]`` table; returns the body and the extra keys present."""
    kind = t.string("kind", choices=kinds)
    shape_keys = {"angle", "length"} if kind in ("rod", "wire") else set()
    t.check_keys(required={"kind", "at", "diameter"} | shape_keys, optional={"id", *extra},
                 context=f" for a {kind}")
    body_id = t.string("id", default_id)
    at = t.pair("at")
    diameter = t.number("diameter", positive=True)
    angle = length = None
    if shape_keys:
        angle = t.number("angle")
        length = t.number("length", positive=True)
        if length < diameter:
            t.fail("length", f"must be at least the diameter ({diameter:g}), got {length:g}")
    return Body(body_id, kind, at, diameter, angle, length), {k for k in extra if k in t}


def geometries(bodies: Sequence[Body]) -> np.ndarray:
    """The cores of ``bodies`` as an object array: each the geometry :meth:`Body.geometry`
    makes, the particles' points made in one call (a thousand one by one took 6 ms)."""
    out = np.empty(len(bodies), dtype=object)
    discs = [i for i, b in enumerate(bodies) if not b.elongated]
    if discs:
        out[discs] = shapely.points(np.array([bodies[i].at for i in discs], dtype=float).reshape(-1, 2))
    for i, b in enumerate(bodies):
        if b.elongated:
            out[i] = b.geometry()
    return out


def check_unique_ids(tables: Sequence[Table], bodies: Sequence[Body]) -> None:
    seen: dict[str, int] = {}
    for i, (t, b) in enumerate(zip(tables, bodies)):
        if b.id in seen:
            t.fail("id", f"duplicate id {b.id!r} (also used by {tables[seen[b.id]].path})")
        seen[b.id] = i


def _slack(r: np.ndarray) -> np.ndarray:
    return TOUCH_EPS * np.maximum(1.0, r)


def outside_area(body: Body, area: Point) -> bool:
    x0, y0, x1, y1 = body.bounds()
    eps = TOUCH_EPS * max(1.0, *area)
    return x0 < -eps or y0 < -eps or x1 > area[0] + eps or y1 > area[1] + eps


def overlapping_pairs(bodies: Sequence[Body], limit: int = 1) -> list[tuple[int, int]]:
    """Pairs ``(i, j)``, i < j, whose footprints overlap (touching is allowed).

    Candidates come from an STRtree over the cores, so this is fast for thousands.
    """
    if len(bodies) < 2:
        return []
    cores = np.array([b.geometry() for b in bodies])
    radii = np.array([b.radius for b in bodies])
    tree = shapely.STRtree(cores)
    i, j = tree.query(cores, predicate="dwithin", distance=2 * radii.max())
    keep = i < j
    i, j = i[keep], j[keep]
    if i.size == 0:
        return []
    reach = radii[i] + radii[j]
    dist = shapely.distance(cores[i], cores[j])
    hit = dist < reach - _slack(reach)
    pairs = sorted(zip(i[hit].tolist(), j[hit].tolist()))
    return pairs[:limit] if limit else pairs


def polygon_overlaps(bodies: Sequence[Body], polygons: Sequence[shapely.Polygon],
                     limit: int = 1) -> list[tuple[int, int]]:
    """Pairs ``(body index, polygon index)`` where a footprint enters a polygon's interior."""
    if not bodies or not polygons:
        return []
    cores = np.array([b.geometry() for b in bodies])
    radii = np.array([b.radius for b in bodies])
    polys = np.array(polygons)
    tree = shapely.STRtree(polys)
    i, k = tree.query(cores, predicate="dwithin", distance=radii.max())
    if i.size == 0:
        return []
    # distance() is 0 inside the polygon; a core strictly farther than r only touches.
    dist = shapely.distance(cores[i], polys[k])
    hit = dist < radii[i] - _slack(radii[i])
    pairs = sorted(zip(i[hit].tolist(), k[hit].tolist()))
    return pairs[:limit] if limit else pairs


def check_placement(noun: str, tables: Sequence[Table], bodies: Sequence[Body], area: Point,
                    region_tables: Sequence[Table], regions: Sequence[shapely.Polygon]) -> None:
    """Every footprint inside the area, none overlapping another or entering a region
    (keep-out, obstacle); the first violation fails with the offending table's path."""
    for t, b in zip(tables, bodies):
        if outside_area(b, area):
            t.fail(None, f"{noun} {b.id!r} lies (partly) outside the area {area[0]:g} x {area[1]:g}")
    for i, j in overlapping_pairs(bodies):
        tables[j].fail(None, f"{noun} {bodies[j].id!r} overlaps {noun} {bodies[i].id!r}")
    for i, k in polygon_overlaps(bodies, regions):
        tables[i].fail(None, f"{noun} {bodies[i].id!r} overlaps {region_tables[k].path}")


#: Largest magnitude of a polygon vertex, nm (1 m, a thousand times any scanner's range):
#: beyond it a polygon's area and validity overflow.
MAX_COORDINATE = 1e9


def polygon_from_table(t: Table, name: str = "polygon") -> tuple[tuple[Point, ...], shapely.Polygon]:
    """A simple polygon with positive area; a closing repeat of the first vertex is allowed."""
    pts = t.points(name, min_len=3)
    far = next((i for i, p in enumerate(pts, start=1) if max(abs(p[0]), abs(p[1])) > MAX_COORDINATE), None)
    if far is not None:     # its area and validity would overflow (shapely warns, then fails)
        x, y = pts[far - 1]
        t.fail(f"{name}[{far}]", f"vertex ({x:g}, {y:g}) lies outside the area: beyond ±{MAX_COORDINATE:g} nm "
                                 f"(1 m), where no area reaches")
    ring = list(pts[:-1]) if len(pts) > 3 and pts[0] == pts[-1] else list(pts)
    if len(ring) < 3:
        t.fail(name, "needs at least 3 distinct vertices")
    poly = shapely.Polygon(ring)
    if not poly.convex_hull.area > 0:
        t.fail(name, "polygon has zero area (its vertices are collinear)")
    if not poly.is_valid:
        reason = shapely.is_valid_reason(poly)
        if "self-intersection" in reason.lower():
            x, y = shapely.get_coordinates(shapely.from_wkt(f"POINT ({reason[reason.find('[') + 1:-1]})"))[0] \
                if "[" in reason else (math.nan, math.nan)
            t.fail(name, f"polygon intersects itself at ({x:g}, {y:g})")
        t.fail(name, f"invalid polygon: {reason}")
    return pts, poly


def polygon_geometry(points) -> shapely.Polygon:
    """A shapely polygon from vertices, with or without the first repeated at the end."""
    pts = tuple(points)
    return shapely.Polygon(pts[:-1] if len(pts) > 3 and pts[0] == pts[-1] else pts)
