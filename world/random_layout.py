"""A layout a scene can fill: ``nanoasm scene random ... --layout OUT.toml --slots N``.

The slots copy the kind and size of ``N`` objects of the scene that can be pushed into
a slot (particles first, nearest the area's centre first; then rods of aspect ratio
L/d below ``ROD_LIMIT``, which the planner pushes as rigid rods, their slots along x),
and lie in a compact cluster about the area's centre: on free ground, at least
``SLOT_GAP`` from one another (room for the tip between filled slots), ``gap`` from
every object and obstacle, and ``EDGE`` of the area's smaller side from its border
(where a drifting full scan may cut them). The scene's obstacles are the layout's
keep-outs. Deterministic: the same scene and count give the same layout.
"""

from __future__ import annotations

import math

import numpy as np
import shapely

from nanoasm.bodies import Body
from nanoasm.errors import InputError

from .scene import Scene

#: Aspect ratio L/d from which a rod is not pushed as a rigid rod (``PlanOptions.rod_limit``).
ROD_LIMIT = 15.0
#: Least clearance between two slots, nm: the tip (radius 10 nm) and the planner's margin
#: (20 nm) on either side of it.
SLOT_GAP = 60.0
#: Share of the area's smaller side kept clear at its border.
EDGE = 0.1
#: Candidate slot centres lie on a square lattice of this pitch, nm (at least; coarser on
#: areas wider than 4 µm: 400 lattice steps across the area).
PITCH = 10.0


def _candidates(scene: Scene, margin: float) -> np.ndarray:
    """``(N, 2)`` lattice points inside the area less ``margin``, nearest the centre first."""
    w, h = scene.area
    pitch = max(PITCH, max(w, h) / 400)
    nx, ny = max(int((w / 2 - margin) // pitch), 0), max(int((h / 2 - margin) // pitch), 0)
    i, j = np.meshgrid(np.arange(-nx, nx + 1), np.arange(-ny, ny + 1))
    i, j = i.ravel(), j.ravel()
    order = np.lexsort((i, j, i * i + j * j))          # by distance, then y, then x
    return np.column_stack([w / 2 + i[order] * pitch, h / 2 + j[order] * pitch])


def _first_free(slot: Body, centres: np.ndarray, geoms: list, reach: np.ndarray, area, margin: float):
    """The first of ``centres`` where ``slot`` (placed there) stays ``margin`` inside the
    area and keeps ``reach[k]`` plus its radius from every ``geoms[k]``; None if none."""
    half = (slot.length - slot.diameter) / 2 if slot.elongated else 0.0
    ext = half + slot.radius
    inside = ((centres[:, 0] - ext >= margin) & (centres[:, 0] + ext <= area[0] - margin)
              & (centres[:, 1] - slot.radius >= margin) & (centres[:, 1] + slot.radius <= area[1] - margin))
    pts = centres[inside]
    if not len(pts):
        return None
    cores = (shapely.points(pts) if half == 0 else
             shapely.linestrings(np.stack([np.column_stack([pts[:, 0] - half, pts[:, 1]]),
                                           np.column_stack([pts[:, 0] + half, pts[:, 1]])], axis=1)))
    bad = np.zeros(len(pts), bool)
    if geoms:
        tree = shapely.STRtree(geoms)
        i, k = tree.query(cores, predicate="dwithin", distance=slot.radius + float(reach.max()))
        hit = shapely.distance(cores[i], np.asarray(geoms, dtype=object)[k]) < slot.radius + reach[k]
        bad[i[hit]] = True
    free = np.flatnonzero(~bad)
    return None if not len(free) else (float(pts[free[0], 0]), float(pts[free[0], 1]))


def _pushable(scene: Scene) -> list[Body]:
    """The objects a slot can take, in the order slots copy them."""
    cx, cy = scene.area[0] / 2, scene.area[1] / 2

    def near(o: Body) -> tuple:
        return math.hypot(o.at[0] - cx, o.at[1] - cy), o.id

    particles = sorted((o for o in scene.objects if o.kind == "particle"), key=near)
    rods = sorted((o for o in scene.objects if o.kind == "rod" and o.aspect < ROD_LIMIT), key=near)
    return particles + rods


def matching_layout(scene: Scene, slots: int, *, gap: float = 50.0, name: str | None = None) -> dict:
    """A ``nanoasm.layout/1`` document (validate it with ``layout_from_dict``) of
    ``slots`` slots that ``scene`` can fill. InputError naming ``--slots`` when the scene
    has too few objects for them or they do not fit."""
    if slots < 1:
        raise InputError(None, "--slots", f"must be at least 1, got {slots}")
    objects = _pushable(scene)
    if slots > len(objects):
        n_p = sum(o.kind == "particle" for o in objects)
        raise InputError(None, "--slots", f"the scene has {len(objects)} object(s) a slot can take ({n_p} "
                                          f"particle(s), {len(objects) - n_p} rod(s) with L/d below "
                                          f"{ROD_LIMIT:g}); ask for at most that many")
    chosen = sorted(objects[:slots], key=lambda o: o.kind != "rod")     # rods need the most room: first
    geoms = [o.geometry() for o in scene.objects] + [ob.geometry() for ob in scene.obstacles]
    reach = [o.radius + gap for o in scene.objects] + [max(gap, SLOT_GAP)] * len(scene.obstacles)
    margin = EDGE * min(scene.area)
    centres = _candidates(scene, margin)
    placed: list[Body] = []
    for k, o in enumerate(chosen, start=1):
        d = round(o.diameter, 1)
        slot = (Body(f"s{k}", "particle", (0.0, 0.0), d) if o.kind == "particle"
                else Body(f"s{k}", "rod", (0.0, 0.0), d, 0.0, round(o.length, 1)))
        at = _first_free(slot, centres, geoms, np.array(reach), scene.area, margin)
        if at is None:
            raise InputError(None, "--slots", f"only {len(placed)} of {slots} slots fit on free ground of the "
                                              f"scene ({SLOT_GAP:g} nm apart, {gap:g} nm from every object); "
                                              "ask for fewer or use a larger --area")
        slot = Body(slot.id, slot.kind, at, slot.diameter, slot.angle, slot.length)
        placed.append(slot)
        geoms.append(slot.geometry())
        reach.append(slot.radius + SLOT_GAP)
    placed.sort(key=lambda b: int(b.id[1:]))
    doc: dict = {"format": "nanoasm.layout/1", "area": [scene.area[0], scene.area[1]],
                 "target": [b.to_dict() for b in placed]}
    if name is not None:
        doc = {"format": doc["format"], "name": name, **{k: v for k, v in doc.items() if k != "format"}}
    if scene.obstacles:
        doc["keepout"] = [{"polygon": [list(p) for p in ob.polygon]} for ob in scene.obstacles]
    return doc
