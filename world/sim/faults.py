"""Rare failures of a push, drawn per push from the world's ``[faults]`` table.

All off by default (probability 0). At the first contact of the tip with an object (the
start of a push) the simulated AFM draws, from its own fault generator and always the
same seven numbers so that one fault's probability never shifts another's draws:

- ``stuck_object``: the object does not move; the tip presses on, the lever's lateral
  force rises with the piezo's overshoot until the tip slips over it;
- ``tip_slip``: the tip slips over the object part-way through the push, after a
  distance drawn uniformly in ``[faults] slip_after_min..slip_after_max`` contact radii;
- ``lost_object``: the object jumps away, a distance drawn uniformly in
  ``[faults] lost_min..lost_max`` nm in a random direction (it leaves the working area in most scenes);
- ``tip_blunting``: the tip's apex radius grows by ``blunting_step`` nm (scans broaden,
  the contact radius grows).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nanoasm.world.params import FaultParams



@dataclass(frozen=True)
class PushFaults:
    """The faults of one push. ``slip_after`` is inf when the tip does not slip."""

    stuck: bool = False
    slip_after: float = math.inf
    lost: bool = False
    blunt: bool = False
    jump: tuple[float, float] = (0.0, 0.0)

    @property
    def any(self) -> bool:
        return self.stuck or self.lost or self.blunt or math.isfinite(self.slip_after)



def draw_push_faults(faults: FaultParams, contact_radius: float, rng: np.random.Generator) -> PushFaults:
    """The faults of a push whose tip–object contact radius is ``contact_radius`` nm."""
    u = rng.random(7)
    stuck = bool(u[0] < faults.stuck_object)
    slip = bool(u[1] < faults.tip_slip)
    lost = bool(u[2] < faults.lost_object)
    blunt = bool(u[3] < faults.tip_blunting)
    lo, hi = faults.slip_after_min, faults.slip_after_max
    slip_after = (lo + (hi - lo) * u[4]) * contact_radius if slip else math.inf
    dist = faults.lost_min + (faults.lost_max - faults.lost_min) * u[5]
    ang = 2.0 * math.pi * u[6]
    jump = (dist * math.cos(ang), dist * math.sin(ang)) if lost else (0.0, 0.0)
    return PushFaults(stuck, slip_after, lost, blunt, jump)
