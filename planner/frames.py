"""Frame checks: a layout's slots against the scan they are to be filled in.

The layout frame is the scan's (its lower-left corner at (0, 0)), or a layout with marks
is mapped into it (:mod:`.alignment`). Either way, a slot outside the scanned area
cannot be filled, and a layout planned against a scan of another size ends in "no path"
for every slot: :func:`check_in_area` refuses it in one line. A slot whose centre lies
on an identified obstacle cannot be filled either: :func:`slots_on_obstacles` names the
obstacle for the plan's ``unfilled`` reason.
"""

from __future__ import annotations

import shapely

from nanoasm.bodies import outside_area
from nanoasm.cad.layout import Layout
from nanoasm.errors import InputError
from nanoasm.listing import first
from nanoasm.schema import Point
from nanoasm.world.environment import Environment


def check_in_area(layout: Layout, area: Point, source: str | None = None) -> None:
    """InputError (naming ``source`` and ``target``) when a slot's footprint leaves the
    scanned ``area`` (w, h, nm) of the layout's frame."""
    outside = [t.id for t in layout.targets if outside_area(t, area)]
    if not outside:
        return
    shown, more = first(outside)
    ids = ", ".join(shown) + (f" and {more} more" if more else "")
    how = (f"after registration ({layout.registration.line()})" if layout.registration is not None
           else "(the layout's frame is the scan's: (0, 0) at its lower-left corner; [[mark]]s register it)")
    (x0, y0, x1, y1) = _extent(layout)
    raise InputError(source, "target", f"{len(outside)} of {len(layout.targets)} slot(s) lie outside the scanned area "
                                       f"{area[0]:g} x {area[1]:g} nm {how}: {ids} (the slots span x {x0:.0f} to "
                                       f"{x1:.0f}, y {y0:.0f} to {y1:.0f} nm)")


def _extent(layout: Layout) -> tuple[float, float, float, float]:
    boxes = [t.bounds() for t in layout.targets]
    return (min(b[0] for b in boxes), min(b[1] for b in boxes), max(b[2] for b in boxes), max(b[3] for b in boxes))


def slots_on_obstacles(layout: Layout, env: Environment) -> dict[str, str]:
    """Slot id -> why it cannot be filled, for every slot whose centre lies on an
    obstacle of ``env`` (numbered from 1 as in the environment's ``obstacles``)."""
    if not env.obstacles or not layout.targets:
        return {}
    polys = [shapely.Polygon(ob.polygon) for ob in env.obstacles]
    tree = shapely.STRtree(polys)
    centres = [shapely.Point(t.at) for t in layout.targets]
    hit_t, hit_o = tree.query(centres, predicate="within")
    out: dict[str, str] = {}
    for i, k in sorted(zip(hit_t.tolist(), hit_o.tolist())):
        t, ob = layout.targets[i], env.obstacles[k]
        if t.id in out:
            continue
        x0, y0, x1, y1 = polys[k].bounds
        out[t.id] = (f"slot lies on an identified obstacle (obstacles[{k + 1}]: {ob.height:.0f} nm high, "
                     f"{x1 - x0:.0f} x {y1 - y0:.0f} nm at ({(x0 + x1) / 2:.0f}, {(y0 + y1) / 2:.0f}))")
    return out
