"""What the first full scan saw, kept apart from the belief: each object's position and
the time its row was recorded, which objects are known from that scan alone, which may
no longer measure drift, and which a push may have disturbed.

A push can shove what lies near its path: the objects within reach of its swept area
(the tip's path, and the object's own from where it was to where it went or was
expected; a rod's whole sweep) are *quarantined*. A quarantined object is no drift
reference until a scan finds it where the drift estimate says it should be
(re-validated); one found elsewhere moved, and the push that most likely moved it is
the nearest of those that came within reach of it since it was last seen.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import shapely

from .json_parts import PartCache, Parts, PartsDict

#: Objects whose footprint comes this close (nm) to a push's swept area are quarantined:
#: a particle's path scatters by a few degrees (70 nm over 2 µm) and a shoved neighbour
#: passes its push on.
QUARANTINE_REACH = 100.0
#: Pushes kept for blaming an object found moved (the most recent ones).
KEPT_PUSHES = 64


@dataclass(frozen=True)
class SweptArea:
    """Where one push may have reached: the pushed object's id, the push's end time (s)
    and the area (layout frame, nm) as a polygon's exterior ring."""

    obj: str
    t: float
    ring: tuple[tuple[float, float], ...]

    def geometry(self) -> shapely.Polygon:
        return shapely.Polygon(self.ring)

    def to_list(self) -> list:
        return [self.obj, self.t, [list(p) for p in self.ring]]

    @classmethod
    def from_list(cls, v) -> SweptArea:
        return cls(str(v[0]), float(v[1]), tuple((float(p[0]), float(p[1])) for p in v[2]))


def swept_area(obj: str, t: float, tip_path, poses, *, tip_radius: float) -> SweptArea:
    """The area a push reached: the tip's path widened by the tip, and the convex hull
    of the object's ``poses`` (Bodies, layout frame: where it started, where it went,
    where it was expected)."""
    parts = [shapely.LineString(np.asarray(tip_path, float)).buffer(tip_radius)
             if len(tip_path) > 1 else shapely.Point(tip_path[0]).buffer(tip_radius)]
    parts += [b.geometry().buffer(b.radius) for b in poses]
    hull = shapely.union_all(parts).convex_hull
    if not isinstance(hull, shapely.Polygon):           # a degenerate path: a point or a line
        hull = hull.buffer(1.0)
    ring = tuple((float(x), float(y)) for x, y in hull.exterior.coords)
    return SweptArea(obj, float(t), ring)


def within_reach(g: shapely.Geometry, objects, reach: float) -> list[str]:
    """Ids of ``objects`` (``(id, body)`` pairs) whose footprint comes closer than
    ``reach`` (nm) to the geometry ``g``. A body's core lies within half its length of its
    centre: beyond ``g``'s box by more than that, its radius and the reach, it is out of
    reach (a 1000-object run: a shapely distance to every object after every push, 7 s
    of its compute)."""
    x0, y0, x1, y1 = g.bounds
    out = []
    for oid, o in objects:
        far = reach + o.radius + 0.5 * (o.length or 0.0)
        x, y = o.at
        if x < x0 - far or x > x1 + far or y < y0 - far or y > y1 + far:
            continue
        if shapely.distance(g, o.geometry()) - o.radius < reach:
            out.append(oid)
    return out


@dataclass
class References:
    """The first full scan's record of the objects (layout frame, nm; instrument s).

    ``first_seen``: position and row time of every identified object. ``raw``: objects
    seen only in that scan (their positions carry their row's drift). ``gated``: objects
    a drift measurement gated out (they moved on their own). ``quarantine``: objects a
    push came within reach of -> the pushed object's id; ``pushes``: the latest pushes'
    swept areas, for blame."""

    first_seen: dict[str, tuple[np.ndarray, float]] = field(default_factory=dict)
    raw: set[str] = field(default_factory=set)
    gated: set[str] = field(default_factory=set)
    quarantine: dict[str, str] = field(default_factory=dict)
    pushes: list[SweptArea] = field(default_factory=list)
    notes: dict[str, str] = field(default_factory=dict, repr=False)     # why each moved (not kept)
    _first_parts: PartCache = field(default_factory=PartCache, repr=False, compare=False)  # state_dict's
    _push_parts: PartCache = field(default_factory=PartCache, repr=False, compare=False)

    @classmethod
    def of_scan(cls, objects, seen) -> References:
        """From the identified ``objects`` and their sightings ``seen`` (id -> Seen)."""
        return cls({o.id: (np.asarray(o.at, float), seen[o.id].t) for o in objects},
                   {o.id for o in objects})

    def forget(self, obj_id: str) -> None:
        """``obj_id`` was never an object of its own (:meth:`Belief.forget`)."""
        self.first_seen.pop(obj_id, None)
        self.raw.discard(obj_id)
        self.gated.discard(obj_id)
        self.quarantine.pop(obj_id, None)

    def is_reference(self, obj_id: str, pushed, lost) -> bool:
        """Whether an object may measure drift: seen in the full scan, never pushed,
        never gated out, not lost (a quarantined one only once re-validated)."""
        return (obj_id in self.first_seen and obj_id not in pushed
                and obj_id not in self.gated and obj_id not in lost)

    def usable(self, obj_id: str, pushed, lost) -> bool:
        """A reference that may be chosen now: not quarantined either."""
        return self.is_reference(obj_id, pushed, lost) and obj_id not in self.quarantine

    # -- pushes ---------------------------------------------------------------------------
    def pushed_near(self, area: SweptArea, belief) -> list[str]:
        """Record a push's swept area; quarantine the references within reach of it
        (returns them)."""
        self.pushes = [*self.pushes, area][-KEPT_PUSHES:]
        candidates = ((oid, o) for oid, o in belief.objects.items()
                      if oid != area.obj and oid not in belief.lost and oid not in self.gated
                      and oid in self.first_seen)
        hit = []
        for oid in within_reach(area.geometry(), candidates, QUARANTINE_REACH):
            if oid not in self.quarantine:
                hit.append(oid)
            self.quarantine[oid] = area.obj
        return hit

    def revalidate(self, obj_id: str) -> None:
        """A quarantined object was found where it should be."""
        self.quarantine.pop(obj_id, None)

    def blame(self, obj_id: str, at, since: float) -> SweptArea | None:
        """The push that most likely moved ``obj_id`` (last believed at ``at``, layout
        frame) after time ``since``: the nearest swept area within reach, the latest of
        equals; None if no push came within reach."""
        p = shapely.Point(float(at[0]), float(at[1]))
        near = [(shapely.distance(a.geometry(), p), -a.t, a) for a in self.pushes if a.t >= since]
        near = [n for n in near if n[0] < QUARANTINE_REACH + 200.0]
        return min(near, key=lambda n: (n[0], n[1]))[2] if near else None

    def moved(self, obj_id: str, at, since: float) -> str:
        """Mark ``obj_id`` as moved (no reference from now on); says which push most
        likely moved it."""
        self.gated.add(obj_id)
        self.quarantine.pop(obj_id, None)
        a = self.blame(obj_id, at, since)
        why = ("no push came within reach of it" if a is None
               else f"most likely moved by the push of {a.obj} ending at t = {a.t:.0f} s")
        self.notes[obj_id] = why
        return why

    def note(self, obj_id: str) -> str:
        """What :meth:`moved` said of ``obj_id``."""
        return self.notes.get(obj_id, "no push came within reach of it")

    # -- checkpoints ------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """For a checkpoint (JSON types); each first sighting's and swept area's part is the
        same (:func:`~.json_parts.kept`) from one checkpoint to the next while it stands."""
        first = PartsDict(zip(self.first_seen, self._first_parts.parts(
            ((k, (float(a[0]), float(a[1]), float(ts))) for k, (a, ts) in self.first_seen.items()), list)))
        pushes = Parts(self._push_parts.parts(((id(a), a) for a in self.pushes), SweptArea.to_list))
        return PartsDict(raw=sorted(self.raw), no_reference=sorted(self.gated), first_seen=first,
                         quarantine=dict(self.quarantine), pushes=pushes)

    @classmethod
    def from_state(cls, state: dict) -> References:
        return cls({k: (np.array(v[:2], float), float(v[2])) for k, v in state["first_seen"].items()},
                   set(state["raw"]), set(state["no_reference"]), dict(state.get("quarantine", {})),
                   [SweptArea.from_list(v) for v in state.get("pushes", [])])

