"""What the first full scan saw, kept apart from the belief: each object's position and
the time its row was recorded, which objects are known from that scan alone, and which
may no longer measure drift."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class References:
    """The first full scan's record of the objects (layout frame, nm; instrument s).

    ``first_seen``: position and row time of every identified object. ``raw``: objects
    seen only in that scan (their positions carry their row's drift). ``gated``: objects
    a drift measurement gated out (they moved on their own)."""

    first_seen: dict[str, tuple[np.ndarray, float]] = field(default_factory=dict)
    raw: set[str] = field(default_factory=set)
    gated: set[str] = field(default_factory=set)

    @classmethod
    def of_scan(cls, objects, seen) -> References:
        """From the identified ``objects`` and their sightings ``seen`` (id -> Seen)."""
        return cls({o.id: (np.asarray(o.at, float), seen[o.id].t) for o in objects},
                   {o.id for o in objects})

    def is_reference(self, obj_id: str, pushed, lost) -> bool:
        """Whether an object may measure drift: seen in the full scan, never pushed,
        never gated out, not lost."""
        return (obj_id in self.first_seen and obj_id not in pushed
                and obj_id not in self.gated and obj_id not in lost)

    def state_dict(self) -> dict:
        return {"raw": sorted(self.raw), "no_reference": sorted(self.gated),
                "first_seen": {k: [float(a[0]), float(a[1]), float(ts)] for k, (a, ts) in self.first_seen.items()}}

    @classmethod
    def from_state(cls, state: dict) -> References:
        return cls({k: (np.array(v[:2], float), float(v[2])) for k, v in state["first_seen"].items()},
                   set(state["raw"]), set(state["no_reference"]))
