"""Order of the moves: a dependency graph over fills and parkings (networkx).

Nodes are ``("fill", target_id)`` and ``("park", object_id)``. Edges say "before":

* hard: a slot held by another object is cleared first: the holder's own fill, or a
  parking of the holder when it has no slot of its own;
* soft: a move whose straight corridor crosses another slot goes before that slot is
  filled; an object lying in another move's corridor moves first.

Cycles are broken deterministically: a soft edge is dropped (the path planner goes
around), or, for a cycle of hard edges (objects in each other's slots), one holder is
parked first where no later path needs the space.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import networkx as nx
import numpy as np
import shapely

from nanoasm.bodies import Body

Node = tuple[str, str]


def _key(b: Body, grow: float) -> tuple:
    return (b.kind, *b.at, b.diameter, b.angle, b.length, grow)


def _discs(at: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Discs of radii ``r`` about the points ``at`` ``(n, 2)``: the polygons
    ``Point(at).buffer(r, quad_segs=8)`` makes, to the bit (GEOS puts the vertex at angle
    θ at ``x + r cos θ``: the unit circle's own vertices, scaled and moved, are those), in
    one call instead of one buffer each (1000 discs: 23 -> 1.2 ms)."""
    return shapely.polygons(_UNIT[None] * r[:, None, None] + at[:, None, :])


#: The unit circle as ``buffer`` draws it (33 vertices, the first repeated).
_UNIT = shapely.get_coordinates(shapely.Point(0.0, 0.0).buffer(1.0, quad_segs=8))


def _footprint(b: Body, grow: float = 0.0) -> shapely.Geometry:
    """``b``'s footprint grown by ``grow`` nm: the same geometry (shapely's never change)
    for as long as a body of its kind, centre and size is asked for again."""
    return _footprints([b], grow)[0]


def _footprints(bodies: Sequence[Body], grow: float = 0.0) -> list[shapely.Geometry]:
    """:func:`_footprint` of each of ``bodies``, the particles' discs not kept made in one
    call (after the drift estimate changed, a replan's every believed position is new)."""
    keys = [_key(b, grow) for b in bodies]
    if len(_FOOTPRINTS) + len(keys) > FOOTPRINTS_KEPT:
        _FOOTPRINTS.clear()
    out = [_FOOTPRINTS.get(k) for k in keys]
    new = [i for i, g in enumerate(out) if g is None]
    discs = [i for i in new if not bodies[i].elongated]
    if discs:
        made = _discs(np.array([bodies[i].at for i in discs], dtype=float).reshape(-1, 2),
                      np.array([bodies[i].radius + grow for i in discs], dtype=float))
        for i, g in zip(discs, made):
            out[i] = _FOOTPRINTS[keys[i]] = g
    for i in new:
        if out[i] is None:
            b = bodies[i]
            out[i] = _FOOTPRINTS[keys[i]] = b.geometry().buffer(b.radius + grow, quad_segs=8)
    return out


#: Footprints by what makes them: a replan builds the dependency graph over every object
#: again, and between two replans most have not moved (1000 objects: a third of a
#: replan's time was buffering the same discs). At most ten times the largest scene's
#: objects are kept (about 1 kB each), then all are forgotten at once.
_FOOTPRINTS: dict[tuple, shapely.Geometry] = {}
FOOTPRINTS_KEPT = 10_000


def _rod_or_particle_first(t1: str, t2: str, targets: Mapping[str, Body], objects: Mapping[str, Body],
                           slot_obj: Mapping[str, str]) -> str:
    """Of a rod slot and a particle slot whose corridors cross each other's slots, the one
    to fill first: the rod when the particle slot lies on the side of the rod slot's axis
    the rod comes from (a particle there would bar its way in: between electrodes, the
    only way), else the particle (it may have to pass where the rod will lie)."""
    rod, part = (t1, t2) if targets[t1].kind == "rod" else (t2, t1)
    slot = targets[rod]
    th = math.radians(slot.angle or 0.0)
    nx_, ny_ = -math.sin(th), math.cos(th)

    def side(p) -> float:
        return (p[0] - slot.at[0]) * nx_ + (p[1] - slot.at[1]) * ny_

    comes_from = side(objects[slot_obj[rod]].at)
    return rod if comes_from * side(targets[part].at) > 0 else part


def dependency_graph(moves: Sequence[tuple[str, str]], targets: Mapping[str, Body],
                     objects: Mapping[str, Body], fixed_ids: set[str], clearance: float
                     ) -> tuple[nx.DiGraph, dict[str, str]]:
    """Build the graph; returns it and ``blocked`` {target id: holder id} for slots held by
    something that can never move (wires, edge objects)."""
    g = nx.DiGraph()
    slot_of = {o: t for t, o in moves}
    moves_index = {t: i for i, (t, _) in enumerate(moves)}
    slot_obj = dict(moves)
    for t, _ in moves:
        g.add_node(("fill", t))
    blocked: dict[str, str] = {}

    # hard edges: slot holders leave first
    movable = [o for o in objects.values()]
    tree = shapely.STRtree(_footprints(movable))
    slots = dict(zip([t for t, _ in moves], _footprints([targets[t] for t, _ in moves])))
    for t, obj_id in moves:
        slot = slots[t]
        for k in tree.query(slot, predicate="intersects"):
            holder = movable[k]
            if holder.id == obj_id or slot.intersection(_footprint(holder)).area < 1e-6:
                continue
            if holder.id in fixed_ids:
                blocked.setdefault(t, holder.id)
            elif holder.id in slot_of:
                g.add_edge(("fill", slot_of[holder.id]), ("fill", t), hard=True)
            else:
                g.add_edge(("park", holder.id), ("fill", t), hard=True)

    # soft edges: corridors versus slots and versus objects in the way
    corridors = {}
    for t, obj_id in moves:
        o, tg = objects[obj_id], targets[t]
        line = shapely.LineString([o.at, tg.at]) if o.at != tg.at else shapely.Point(o.at)
        # a rod walks by swinging its ends: it sweeps about half its length either side
        reach = o.length / 2 if o.kind == "rod" else o.radius
        corridors[t] = line.buffer(reach + clearance, quad_segs=4)
    ctree_ids = list(corridors)
    ctree = shapely.STRtree([corridors[t] for t in ctree_ids])
    crossing_into = {t2: sorted({ctree_ids[k] for k in ctree.query(_footprint(targets[t2]), predicate="intersects")
                                 if ctree_ids[k] != t2}, key=lambda t: moves_index[t]) for t2, _ in moves}
    crossing = {(t1, t2) for t2, into in crossing_into.items() for t1 in into}
    for t2, _ in moves:
        for t1 in crossing_into[t2]:
            if (t2, t1) in crossing and targets[t1].kind != targets[t2].kind:
                first = _rod_or_particle_first(t1, t2, targets, objects, slot_obj)
                if first != t1:
                    continue
            if not g.has_edge(("fill", t2), ("fill", t1)):
                g.add_edge(("fill", t1), ("fill", t2), hard=False)
    for t2, obj2 in moves:
        for k in ctree.query(_footprint(objects[obj2]), predicate="intersects"):
            t1 = ctree_ids[k]
            if t1 == t2 or g.has_edge(("fill", t2), ("fill", t1)) or g.has_edge(("fill", t1), ("fill", t2)):
                continue
            if targets[t1].kind != targets[t2].kind and \
                    _rod_or_particle_first(t1, t2, targets, objects, slot_obj) == t1:
                # a particle in a rod's way whose slot lies on the side the rod comes from
                # would bar the way for good once there: the rod goes first, around it
                # (the bundled bowtie: its left triangle filled first shut the rod out)
                continue
            g.add_edge(("fill", t2), ("fill", t1), hard=False)
    return g, blocked


def break_cycles(g: nx.DiGraph, slot_of: Mapping[str, str]) -> list[str]:
    """Make ``g`` acyclic in place; returns objects that must be parked to do so."""
    parked: list[str] = []
    while True:
        try:
            cycle = nx.find_cycle(g)
        except nx.NetworkXNoCycle:
            return parked
        soft = sorted((u, v) for u, v, *_ in cycle if not g.edges[u, v].get("hard"))
        if soft:
            g.remove_edge(*soft[-1])
            continue
        # objects sitting in each other's slots: park the holder of the first edge
        u, v = min((u, v) for u, v, *_ in cycle)
        holder = next(o for o, t in slot_of.items() if t == u[1])
        g.remove_edge(u, v)
        g.add_edge(("park", holder), v, hard=True)
        parked.append(holder)


def order(moves: Sequence[tuple[str, str]], targets: Mapping[str, Body], objects: Mapping[str, Body],
          fixed_ids: set[str], clearance: float, effort: Mapping[str, float]
          ) -> tuple[list[Node], dict[str, str]]:
    """Deterministic order of fills and parkings: parkings, then rod slots (a rod needs
    room to swing through: it goes before the nimble particles close its way), then
    particle slots; ties go to the cheaper move first."""
    g, blocked = dependency_graph(moves, targets, objects, fixed_ids, clearance)
    for t in blocked:
        g.remove_node(("fill", t))
    break_cycles(g, {o: t for t, o in moves})

    def key(n: Node) -> tuple:
        if n[0] == "park":
            return (0, 0.0, n[1])
        return (1 if targets[n[1]].kind == "rod" else 2, effort.get(n[1], 0.0), n[1])

    return list(nx.lexicographical_topological_sort(g, key=key)), blocked
