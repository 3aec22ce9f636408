"""Planner settings with their defaults."""

from __future__ import annotations

import math
from dataclasses import dataclass

#: OMPL planners by the names the CLI accepts.
PLANNERS = ("rrtconnect", "rrt", "rrtstar", "informedrrtstar", "bitstar", "prm", "prmstar",
            "fmt", "kpiece", "bkpiece", "lbkpiece")


@dataclass(frozen=True)
class PlanOptions:
    """How to plan.

    Parameters
    ----------
    tip_radius : float
        AFM tip radius, nm; paths keep object radius + tip radius + ``margin`` clear.
    margin : float
        Extra clearance, nm, around every path against obstacles, keep-outs and objects.
    lead : float
        The tip is put down this far (nm) short of contact, behind the object, so that an
        object found a little off does not end up under the tip.
    planner : str
        OMPL planner for paths that a straight line cannot take (see ``PLANNERS``).
    budget : float
        Planning effort for one path, counted in work, not time, so that a plan does not
        depend on how busy the machine is: OMPL may run ``ITERATIONS_PER_UNIT`` (4000)
        iterations a unit, the rod search ``EXPANSIONS_PER_UNIT`` (1500) expansions a
        unit (:mod:`nanoasm.planner.ompl_setup`); one unit is about a second here. The
        threaded planners (prm, prmstar) get one second of wall clock a unit instead.
    rod_limit : float
        Largest aspect ratio σ = L/d pushed as a rigid rod (seed §4.3: 15).
    min_confidence : float
        Objects identified with less confidence are never assigned.
    seed : int
        Seeds OMPL's sampler so a plan is reproducible.
    rod_swing : float
        Largest rotation, degrees, of one rod push (one half of a zigzag step).
    rod_push_point : float
        Push point of rod pushes as a fraction of the length from the pushed end; kept
        well away from the bifurcation at L/2 (seed eq. 4.10).
    """

    tip_radius: float = 10.0
    margin: float = 20.0
    lead: float = 20.0
    planner: str = "rrtconnect"
    budget: float = 1.0
    rod_limit: float = 15.0
    min_confidence: float = 0.5
    seed: int = 0
    rod_swing: float = 20.0
    rod_push_point: float = 0.1

    def __post_init__(self) -> None:
        for name in ("tip_radius", "margin", "lead", "budget", "rod_limit", "rod_swing"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0) and not (name in ("margin", "lead") and v == 0):
                raise ValueError(f"{name} must be positive and finite, got {v!r}")
        if self.planner not in PLANNERS:
            raise ValueError(f"planner must be one of {', '.join(PLANNERS)}, got {self.planner!r}")
        if not 0.0 <= self.min_confidence <= 1.0:
            raise ValueError(f"min_confidence must be in [0, 1], got {self.min_confidence!r}")
        if not 0.0 <= self.rod_push_point <= 0.3:
            raise ValueError(f"rod_push_point must be in [0, 0.3], got {self.rod_push_point!r}")
        if not 0.0 < self.rod_swing <= 60.0:
            raise ValueError(f"rod_swing must be in (0, 60], got {self.rod_swing!r}")
        if self.seed < 0:
            raise ValueError(f"seed must not be negative, got {self.seed!r}")

    @property
    def clearance(self) -> float:
        """What every path keeps clear beyond the footprints: tip radius + margin."""
        return self.tip_radius + self.margin
