"""Which object a local scan saw: a sighting associated with the belief, gated by where
each object can be and by its size, so that a neighbour is never silently taken for the
object looked for.

A located object (centre ``z`` in the layout frame with covariance ``R``, highest point
``h`` above the substrate) is compared with every believed object ``c`` that is not lost:

- **position gate**: ``|z - x_c| <= g_c``, where ``g_c`` is ``c``'s search radius (3σ of
  where it is believed, :meth:`~.context.RunContext.r_max`; the object looked for may be
  given a wider one, e.g. a push's scatter, or the lost-object search's whole field) plus
  3σ of the measurement along its worst direction;
- **size gate**: ``h`` is an object of ``c``'s height (its diameter, particle or rod):
  ``SIZE_LOW d - 3 noise <= h <= SIZE_HIGH d + 3 noise``. The lower bound is loose
  because a line that grazes a particle's rim reads less than its summit.

The answer (:class:`Association`):

- ``match``: the object looked for passes both gates and no other does;
- ``ambiguous``: it does, and so do others (``others``, most likely first): the caller
  scans where those are believed (:func:`~.scan_steps.locate` does) before it decides,
  never swapping silently;
- ``other``: only other objects pass (the scan found a neighbour);
- ``new``: none does: something is there that no believed object can be (the caller adds
  it to the belief as a new object; the one looked for is not found).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .edges import TALLER

#: A sighting's height may read this share of an object's diameter (a line off the summit).
SIZE_LOW = 0.7
#: ... and at most this share (an object this much higher is another object; a line's
#: edges never take one, :data:`~.edges.TALLER`).
SIZE_HIGH = TALLER
#: Height noise (nm) assumed when the lines report none.
HEIGHT_NOISE = 0.5


@dataclass(frozen=True)
class Candidate:
    """A believed object a sighting is compared with: layout position (nm), its gate
    radius (3σ, nm) and its height (nm)."""

    id: str
    at: tuple[float, float]
    gate: float
    height: float


@dataclass(frozen=True)
class Association:
    """What a sighting is (see the module docstring). ``distance``: the sighting's
    distance (nm) from where the object looked for is believed; ``others``: the other
    objects that pass both gates, most likely first."""

    kind: str                      # "match" | "ambiguous" | "other" | "new"
    distance: float
    others: tuple[str, ...] = ()

    @property
    def accepted(self) -> bool:
        return self.kind == "match"

    def text(self, obj_id: str) -> str:
        """One line for the run's events."""
        if self.kind == "match":
            return f"{obj_id} found {self.distance:.0f} nm from where it was believed"
        if self.kind == "ambiguous":
            return (f"{obj_id}: the object found {self.distance:.0f} nm from it could also be "
                    f"{', '.join(self.others)}")
        if self.kind == "other":
            return f"{obj_id}: the object found is {self.others[0]}, not {obj_id}"
        return f"{obj_id}: the object found {self.distance:.0f} nm away is none that is believed to be near"


def size_ok(height: float, diameter: float, noise: float) -> bool:
    """Whether a sighting ``height`` nm high can be an object of ``diameter`` nm."""
    slack = 3.0 * max(noise, HEIGHT_NOISE)
    return SIZE_LOW * diameter - slack <= height <= SIZE_HIGH * diameter + slack


def associate(expected: Candidate, others: list[Candidate], z, cov, height: float | None,
              noise: float = HEIGHT_NOISE) -> Association:
    """Associate a sighting at ``z`` (layout frame, covariance ``cov`` nm², height
    ``height`` nm or None when no line measured it) with the object ``expected`` looked
    for, among ``others`` (every other believed object that is not lost)."""
    z = np.asarray(z, float)
    meas = 3.0 * math.sqrt(max(float(np.linalg.eigvalsh(np.asarray(cov, float))[-1]), 0.0))

    def passes(c: Candidate) -> tuple[bool, float]:
        d = math.dist(z, c.at)
        fits = height is None or size_ok(height, c.height, noise)
        return fits and d <= c.gate + meas, d / (c.gate + meas)

    ok_e, _ = passes(expected)
    near = sorted((q, c.id) for c in others for ok, q in [passes(c)] if ok)
    ids = tuple(i for _, i in near)
    distance = math.dist(z, expected.at)
    if ok_e:
        return Association("ambiguous" if ids else "match", distance, ids)
    return Association("other" if ids else "new", distance, ids)


def sighting(res) -> tuple[float | None, float]:
    """The highest point (nm above the substrate) the lines of a located scan result
    crossed, and their height noise; (None, noise) when no line found the object."""
    peaks = [ln.edges.peak for ln in res.lines if ln.edges.found and ln.edges.peak is not None]
    noises = [ln.edges.noise for ln in res.lines if ln.edges.found]
    return (max(peaks) if peaks else None), (max(noises) if noises else HEIGHT_NOISE)
