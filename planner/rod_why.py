"""Why a rod's search found no way into its slot, in words a user can act on: which
stage gave up (the direct search, the SE(2) guide, a leg along it, the last pushes),
where the rod stood nearest the slot, and what lies in its way there and along the
straight way (the objects by id, keep-outs, marks and obstacles by number).
"""

from __future__ import annotations

import math

import shapely

from nanoasm.bodies import Body


def fixed_names(layout, obstacles, fixed_ids) -> tuple[str, ...]:
    """Names of a :class:`~.freespace.FreeSpace`'s fixed entries in the order the planner
    builds them: the layout's regions (keep-outs, then marks), the obstacles (each with
    its centre), then the objects that never move."""
    out = [f"keep-out {k + 1}" for k in range(len(layout.keepouts))]
    out += [f"mark {k + 1}" for k in range(len(layout.marks))]
    for k, ob in enumerate(obstacles):
        c = shapely.Polygon(ob.polygon).representative_point()
        out.append(f"obstacle {k + 1} near ({c.x:.0f}, {c.y:.0f})")
    return tuple(out) + tuple(f"{i} (not to be moved)" for i in fixed_ids)


def where(pose: Body, goal: Body, what: str = "the slot") -> str:
    """``pose`` and how far it is from ``goal`` (``what``): centre, axis angle, distance
    and turn."""
    turn = abs(math.remainder(goal.angle - pose.angle, 180.0))
    return (f"({pose.at[0]:.0f}, {pose.at[1]:.0f}) at {round(pose.angle) % 180}°, "
            f"{math.dist(pose.at, goal.at):.0f} nm and {turn:.0f}° from {what}")


def in_the_way(space, names: tuple[str, ...], geom, radius: float, ignore: str,
               clearance: float | None = None) -> list[str]:
    """What lies within the clearance of the footprint (geom, radius): the movable
    objects by id, then the fixed entries by name."""
    movable = space.blockers(geom, radius, (ignore,), clearance)
    fixed = sorted(int(i) for i in space.fixed_hits(geom, radius, clearance))
    return movable + [name(names, i) for i in fixed]


def name(names: tuple[str, ...], i: int) -> str:
    """Fixed entry ``i`` by its name (by its number where none was given)."""
    return names[i] if i < len(names) else f"fixed entry {i + 1}"


def listed(items: list[str], most: int = 4) -> str:
    """``a, b and c`` (``and N more`` past ``most``)."""
    if len(items) > most:
        items = items[:most] + [f"{len(items) - most} more"]
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


def straight_way(space, names: tuple[str, ...], rod: Body, goal: Body) -> str:
    """What the straight way from ``rod`` to ``goal`` (the hull of the two footprints'
    cores) runs into, with the space's clearance; empty when nothing."""
    hull = shapely.union(rod.geometry(), goal.geometry()).convex_hull
    hits = in_the_way(space, names, hull, rod.radius, rod.id)
    return f"the straight way is blocked by {listed(hits)}" if hits else "the straight way is clear"


def stuck(space, names: tuple[str, ...], pose: Body, goal: Body, clearance: float | None,
          what: str = "the slot") -> str:
    """Where a search stood nearest its goal (``what``), and what is within its clearance
    there."""
    hits = in_the_way(space, names, pose.geometry(), pose.radius, pose.id, clearance)
    return f"nearest at {where(pose, goal, what)}" + (f", beside {listed(hits)}" if hits else "")
