"""The simulated world's contact space: footprints that the tip moves, turns and bends.

:class:`SimContacts` extends :class:`nanoasm.world.sim.contact_space.ContactSpace` (translation
pushes with chain shoving, uniform-grid index) with what the simulated AFM needs beyond
translation:

- *units grouped into objects*: a rigid particle or rod is one unit; a flexible wire is a
  chain of capsule segments, one unit each, all in one group; units of one group never
  collide with each other (a wire's neighbouring segments share their end points);
- :meth:`SimContacts.place`: put a unit at a new pose (a rod that rotated, a wire
  segment that bent, an object that jumped away) without resolving contacts;
- :meth:`SimContacts.settle`: resolve the contacts around a unit that was placed, with
  that unit as the driver (it never yields; what it touches is shoved, in chains);
- :meth:`SimContacts.near_other`: whether a unit ends within a gap of another object.

It reaches into the base class's index (``_a``, ``_b``, ``_centre``, ``_bodies``,
``_index``, ``_neighbours``, ``_resolve``, ``_near_other``); those hooks are candidates
for public methods of :class:`ContactSpace`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from nanoasm.bodies import Body

from .contact_space import ContactSpace


class SimContacts(ContactSpace):
    """Units (footprints) of the simulated objects, with the owning object of each unit.

    Parameters
    ----------
    units : sequence of Body
        One footprint per unit (particles, rods, wire segments as rods).
    groups : sequence of int
        ``groups[i]`` is the object that unit ``i`` belongs to.
    """

    def __init__(self, units: Sequence[Body], groups: Sequence[int], cell: float | None = None):
        if len(groups) != len(units):
            raise ValueError(f"need one group per unit, got {len(groups)} for {len(units)} units")
        self.groups = np.asarray(groups, dtype=np.int64)
        super().__init__(units, cell)

    # -- the base class's neighbour query, without a unit's own group ---------------------------
    def _neighbours(self, i: int, margin: float = 0.0) -> list[int]:
        g = self.groups[i]
        return [j for j in super()._neighbours(i, margin) if self.groups[j] != g]

    # -- state -----------------------------------------------------------------------------------
    def unit(self, i: int) -> Body:
        """The current footprint of unit ``i``."""
        return self._bodies[i]

    def cores(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(a, b, r)``: core end points ``(n, 2)`` and radii ``(n,)`` of every unit (views)."""
        return self._a, self._b, self._r

    def place(self, i: int, body: Body) -> None:
        """Put unit ``i`` at ``body``'s pose (same radius); contacts are not resolved."""
        if not math.isclose(body.radius, self._r[i], rel_tol=1e-12):
            raise ValueError(f"unit {i}: a placed body keeps its radius {self._r[i]:g}, got {body.radius:g}")
        a, b = body.core()
        self._a[i] = a
        self._b[i] = b
        self._centre[i] = body.at
        self._bodies[i] = body
        self._index(i)

    def settle(self, i: int, hint: tuple[float, float] = (1.0, 0.0)) -> list[int]:
        """Resolve contacts around unit ``i`` as the driver; returns the other units moved.

        ``hint`` is the direction to separate along when two cores cross exactly.
        """
        moved: set[int] = set()
        norm = math.hypot(*hint)
        hint = (hint[0] / norm, hint[1] / norm) if norm > 0 else (1.0, 0.0)
        self._resolve(i, hint, moved)
        moved.discard(i)
        for m in moved:
            self._bodies[m] = _moved(self._bodies[m], self._centre[m])
        return sorted(moved)

    def near_other(self, i: int, within: float) -> bool:
        """True if unit ``i`` lies within ``within`` nm of a unit of another object."""
        return self._near_other(i, within)


def _moved(body: Body, centre: np.ndarray) -> Body:
    x, y = float(centre[0]), float(centre[1])
    return Body(body.id, body.kind, (x, y), body.diameter, body.angle, body.length)
