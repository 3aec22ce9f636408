"""The state the pushing physics works on: objects, contact units, wires, obstacles, tip.

:class:`PushWorld` keeps the truth of every object in a
:class:`~nanoasm.world.sim.contacts.SimContacts` (one unit per particle or rod, one per
wire segment) and answers the geometric questions of :mod:`nanoasm.world.sim.push`:
which objects lie near a box (through the contact space's grid, so idle objects far from
the tip cost nothing), the gap from the tip to an object, the height the apex rides at
over it, whether a pose enters an obstacle; it moves whole objects (translate, jump) and
keeps a wire's segments joined after other objects shoved them.
"""

from __future__ import annotations

import math

import numpy as np
import shapely

from nanoasm.bodies import Body
from nanoasm.world.params import WorldParams
from nanoasm.world.tipimage import Tip, ball_image, plateau_image, segment_distance, tip_reach

from .contacts import SimContacts
from .objects import Kind, ObjectTable
from .wire import chord_body, segment_body, sync_nodes


#: nm by which one step of a push may bring an object that lies in an obstacle nearer it
#: and still count as moving along it (rounding in the step: 4e-6 nm seen).
DEEPER = 1e-3


class PushWorld:
    """Objects and their contacts, the tip's radius, the pushes in progress."""

    def __init__(self, table: ObjectTable, units: list[Body], groups: list[int],
                 wires: dict[int, np.ndarray], params: WorldParams, obstacles,
                 rng_faults: np.random.Generator, rng_vdw: np.random.Generator):
        self.table = table
        self.contacts = SimContacts(units, groups)
        self.wires = {k: np.array(v, float) for k, v in wires.items()}
        self._initial_nodes = {k: v.copy() for k, v in self.wires.items()}
        self._truth_order: tuple[list[int], list[int]] | None = None     # truth()'s units, its wires
        self.episodes: dict = {}
        self.tip_radius = float(params.tip.radius)
        self.half_angle = float(params.tip.half_angle)
        self.f_ts = float(params.adhesion.tip_substrate)
        self.mu_ts = float(params.friction.mu_ts)
        cl = params.cantilever
        self.k_stick = cl.lateral_gain / max(cl.C1, 1e-3)   # nN/nm: lateral stiffness of the lever
        self.faults = params.faults
        self.sim = params.sim
        self.release = float(params.sim.release)
        self.vdw = params.vdw
        self.rng_faults = rng_faults
        self.rng_vdw = rng_vdw
        self.lag = (0.0, 0.0)      # tip offset due to the lateral force at this step, nm
        self.version = 0
        self.pushes = self.slips = self.blunted = self.steps = 0
        self.obstacles = [o.geometry() for o in obstacles]
        self.obstacle_height = np.array([float(o.height) for o in obstacles])
        for poly in self.obstacles:
            shapely.prepare(poly)
        self._obstacle_box = np.array([p.bounds for p in self.obstacles], float).reshape(-1, 4)
        _, _, r = self.contacts.cores()
        self.max_height = float(2.0 * r.max()) if r.size else 0.0

    # -- geometry --------------------------------------------------------------------------------
    @property
    def tip(self) -> Tip:
        return Tip(self.tip_radius, self.half_angle)

    def radius(self, o: int) -> float:
        return self.table.bodies[o].radius

    def units_of(self, o: int) -> range:
        f = int(self.table.first_unit[o])
        return range(f, f + int(self.table.n_units[o]))

    def core_distance(self, o: int, p) -> float:
        """Distance (nm) from ``p`` to the object's core (centre, axis or wire polyline)."""
        a, b, _ = self.contacts.cores()
        if self.table.kind[o] == Kind.PARTICLE:
            u = int(self.table.first_unit[o])
            return math.hypot(p[0] - a[u, 0], p[1] - a[u, 1])
        us = self.units_of(o)
        return float(min(segment_distance(p[0], p[1], a[u], b[u]) for u in us))

    def normal(self, o: int, p) -> tuple[tuple[float, float], float]:
        """``((nx, ny), penetration)``: unit vector from ``p`` to the nearest core point of
        the object, and how far (nm) the tip at ``p`` lies inside the contact distance."""
        a, b, _ = self.contacts.cores()
        best = (math.inf, 0.0, 0.0)
        for u in self.units_of(o):
            d = b[u] - a[u]
            n2 = float(d @ d)
            f = 0.0 if n2 == 0 else min(max(float((np.asarray(p) - a[u]) @ d) / n2, 0.0), 1.0)
            cx, cy = a[u] + f * d
            dist = math.hypot(cx - p[0], cy - p[1])
            if dist < best[0]:
                best = (dist, cx - p[0], cy - p[1])
        dist, vx, vy = best
        unit = (vx / dist, vy / dist) if dist > 0 else (1.0, 0.0)
        return unit, self.radius(o) + self.tip_radius - dist

    def gap(self, o: int, p) -> float:
        """Clearance (nm) between the tip at ``p`` and the object; negative when they touch."""
        return self.core_distance(o, p) - self.radius(o) - self.tip_radius

    def ride_height(self, o: int, p) -> float:
        """Height (nm) of the apex riding over the object with the tip at ``p``: from 0 at
        the contact distance rc (where the push model puts the first touch) to the top
        2r over the core, ``2r (1 - (ρ/rc)²)``."""
        r = self.radius(o)
        q = self.core_distance(o, p) / (r + self.tip_radius)
        return max(0.0, 2.0 * r * (1.0 - q * q))

    def candidates(self, lo, hi, reach: float) -> np.ndarray:
        """Objects whose footprints come within ``reach`` nm of the box ``lo``-``hi`` (sorted).

        The contact space's grid gives the units near the box (a chunk's box spans a few
        cells), so the cost follows the objects near the tip, not the sample's count."""
        a, b, r = self.contacts.cores()
        if r.size == 0:
            return np.zeros(0, np.int64)
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        near = self.contacts.units_near(lo - reach - 1.0, hi + reach + 1.0)   # 1 nm: a superset to rounding
        if near is not None:
            a, b, r = a[near], b[near], r[near]
        ulo = np.minimum(a, b) - (r + reach)[:, None]
        uhi = np.maximum(a, b) + (r + reach)[:, None]
        hit = np.all((ulo <= hi) & (uhi >= lo), axis=1)
        groups = self.contacts.groups if near is None else self.contacts.groups[near]
        return np.unique(groups[hit])

    def unit_gaps(self, units: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Least clearance (nm) from points ``(x, y)`` ``(n,)`` to the given units' footprints."""
        a, b, r = self.contacts.cores()
        out = np.full(np.shape(x), np.inf)
        for blk in _blocks(units):
            d = _segment_distances(x, y, a[blk], b[blk]) - r[blk]
            out = np.minimum(out, d.min(axis=1))
        return out

    def unit_heights(self, units: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Apex heights (nm, ≥ 0) over the given units at points ``(x, y)`` ``(n,)``: the
        tip's dilation of each footprint, as a scan images it."""
        a, b, r = self.contacts.cores()
        tip = self.tip
        h = np.zeros(np.shape(x))
        for blk in _blocks(units):
            d = _segment_distances(x, y, a[blk], b[blk])
            h = np.maximum(h, ball_image(d, r[blk], tip).max(axis=1))
        return h

    def obstacle_heights(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Apex heights (nm, ≥ 0) over the obstacles at points ``(x, y)`` ``(n,)``."""
        h = np.zeros(np.shape(x))
        if not self.obstacles or h.size == 0:
            return h
        tip = self.tip
        for k, poly in enumerate(self.obstacles):
            reach = float(tip_reach(self.obstacle_height[k], tip))
            x0, y0, x1, y1 = self._obstacle_box[k]
            near = np.flatnonzero((x >= x0 - reach) & (x <= x1 + reach) & (y >= y0 - reach) & (y <= y1 + reach))
            if near.size:
                d = shapely.distance(poly, shapely.points(x[near], y[near]))
                h[near] = np.maximum(h[near], plateau_image(d, self.obstacle_height[k], tip))
        return np.maximum(h, 0.0)

    def hits_obstacle(self, body: Body, before: Body | None = None) -> bool:
        """True if ``body``'s footprint enters an obstacle; given the pose ``before`` the
        move, only if it enters deeper than it lay there (an object already against an
        obstacle may leave it, or move along it)."""
        if not self.obstacles:
            return False
        x0, y0, x1, y1 = body.bounds()
        box = self._obstacle_box
        near = np.flatnonzero((box[:, 0] <= x1) & (box[:, 2] >= x0) & (box[:, 1] <= y1) & (box[:, 3] >= y0))
        if not near.size:
            return False
        geom = body.geometry()
        for k in near:
            d = shapely.distance(self.obstacles[k], geom)
            if d < body.radius * (1 - 1e-9) and (
                    before is None or d < shapely.distance(self.obstacles[k], before.geometry()) - DEEPER):
                return True
        return False

    def wire_hits_obstacle(self, o: int, nodes: np.ndarray) -> bool:
        if not self.obstacles:
            return False
        d = self.table.bodies[o].diameter
        return any(self.hits_obstacle(segment_body("s", nodes[j], nodes[j + 1], d))
                   for j in range(len(nodes) - 1))

    def near_other(self, o: int) -> bool:
        return any(self.contacts.near_other(u, self.vdw.range) for u in self.units_of(o))

    # -- moving whole objects -------------------------------------------------------------------
    def place_wire(self, o: int, nodes: np.ndarray, hint) -> set[int]:
        """Put wire ``o`` on ``nodes`` and resolve its contacts; returns the units moved."""
        self.wires[o] = nodes
        d = self.table.bodies[o].diameter
        units = list(self.units_of(o))
        body_id = self.table.bodies[o].id
        for j, u in enumerate(units):
            self.contacts.place(u, segment_body(f"{body_id}#{j}", nodes[j], nodes[j + 1], d))
        moved = set(units)
        for u in units:
            moved.update(self.contacts.settle(u, hint))
        self.version += 1
        return moved

    def translate(self, o: int, d: tuple[float, float]) -> set[int]:
        """Move object ``o`` by ``d`` nm, shoving what it meets; returns the units moved."""
        if self.table.kind[o] == Kind.WIRE:
            moved = self.place_wire(o, self.wires[o] + np.asarray(d, float), d)
        else:
            moved = set(self.contacts.push(int(self.table.first_unit[o]), d))
        self.after_shove(moved, o)
        return moved

    def jump(self, o: int, d: tuple[float, float]) -> None:
        """A lost object: it leaves the tip for a spot ``d`` nm away."""
        self.translate(o, d)

    def after_shove(self, moved: set[int], driver: int) -> None:
        """Rejoin the segments of wires (other than ``driver``) that contacts shoved."""
        self.version += 1
        if not self.wires:
            return
        groups = {int(self.contacts.groups[u]) for u in moved}
        a, b, _ = self.contacts.cores()
        for w in sorted(g for g in groups if g in self.wires and g != driver):
            us = list(self.units_of(w))
            nodes = sync_nodes(self.wires[w], a[us], b[us])
            moved.update(self.place_wire(w, nodes, (1.0, 0.0)))

    # -- views -----------------------------------------------------------------------------------
    def unit_bodies(self) -> tuple[Body, ...]:
        """Every unit's footprint (wire segments as rods): what a scan images."""
        return self.contacts.bodies

    def truth(self) -> tuple[Body, ...]:
        """The objects in the sample frame, a wire as the rod on its end-to-end chord (the
        objects' kinds and first footprints read once: a dry-run asks after every push)."""
        if self._truth_order is None:
            kind, first = self.table.kind, self.table.first_unit
            self._truth_order = ([int(f) for f in first], [o for o in range(len(kind)) if kind[o] == Kind.WIRE])
        firsts, wires = self._truth_order
        unit = self.contacts.unit
        out = [unit(f) for f in firsts]
        for o in wires:
            body, nodes = self.table.bodies[o], self.wires[o]
            same = np.array_equal(nodes, self._initial_nodes[o])
            out[o] = body if same else chord_body(body.id, nodes, body.diameter)
        return tuple(out)


def _blocks(units: np.ndarray, size: int = 256):
    units = np.asarray(units, np.int64)
    return (units[i:i + size] for i in range(0, units.size, size))


def _segment_distances(x: np.ndarray, y: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(n, c)`` distances from points ``(x, y)`` ``(n,)`` to segments ``a``-``b`` ``(c, 2)``."""
    d = b - a
    n2 = np.einsum("ij,ij->i", d, d)
    ux = np.asarray(x, float)[:, None] - a[None, :, 0]
    uy = np.asarray(y, float)[:, None] - a[None, :, 1]
    f = np.clip((ux * d[:, 0] + uy * d[:, 1]) / np.where(n2 > 0, n2, 1.0), 0.0, 1.0)
    return np.hypot(ux - f * d[:, 0], uy - f * d[:, 1])
