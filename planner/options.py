"""Planner settings with their defaults."""

from __future__ import annotations

from dataclasses import dataclass

from nanoasm.param import param, validate

#: How a layout with alignment marks is registered (:mod:`nanoasm.planner.alignment`).
ALIGNS = ("rigid", "similarity", "none")

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
        Largest rotation, degrees, of one rod push (one half of a zigzag step). 45° by
        default: over 10 seeds each of the rods, mixed and device families it took 0.45,
        0.58 and 0.74 times the pushes a run of 20° (median) and filled as many rod slots
        or more (``bench/RESULTS_rods.md``); the search still has swings of a half and a
        quarter of it, and the finish down to 0.5°.
    rod_push_point : float
        Push point of rod pushes as a fraction of the length from the pushed end; kept
        well away from the bifurcation at L/2 (seed eq. 4.10). 0.2 by default (measured
        with the 45° swing; issue 14's audit found the tip slipping off rods beyond
        l ≈ 0.32 L at the instrument's preload).
    rod_direct : str
        When a rod's lattice search heads straight for its goal before an SE(2) path is
        sought: ``always`` (the default), or ``clear``: only when the rod's straight sweep
        from where it is to its goal is clear. A search whose straight way is blocked
        spends its whole budget before it gives up (issue 14: 22 of 30 such searches
        failed on the bowtie, 54 s of 60), so ``clear`` plans the bowtie's first plan in
        2.4-2.8 s instead of 6.1-6.4; but where a direct search would still have got
        through, the SE(2) path's detour costs pushes: over 10 seeds, rods 24.5 -> 33
        pushes a run, rodgap 101 -> 133 and 3.4 -> 9.6 min of wall time, mixed one slot
        fewer (bench/RESULTS_rods.md).
    rod_search : str
        A rod's lattice search (weighted A*): ``greedy`` (the default), or ``refine``: the
        way the direct search found toward a slot not enclosed by fixed things is searched
        again less greedily for fewer pushes (legs along an SE(2) path are not: refined,
        they lost the bowtie's rod slot on 3 of 10 seeds). Over 10 seeds (2026-12-07) pushes
        per rod 22 -> 17 on rods and 26 -> 24 on mixed, rod time per slot 186.5 -> 155.8 s
        and 299 -> 271 s; device unchanged (its slots are enclosed), the bowtie 70/70 over
        --seed 1-10; but rodgap loses a rod slot (bench/RESULTS_rods.md).
    align : str
        How a layout with alignment marks is registered to the scan before planning
        (:mod:`nanoasm.planner.alignment`): ``rigid`` (rotation and translation),
        ``similarity`` (the scale too) or ``none`` (the layout frame is the scan's).
    """

    tip_radius: float = param(10.0, "nm", "AFM tip radius", positive=True)
    margin: float = param(20.0, "nm", "extra clearance of every path", nonnegative=True)
    lead: float = param(20.0, "nm", "the tip is put down this far short of contact", nonnegative=True)
    planner: str = param("rrtconnect", "", "OMPL planner for paths a straight line cannot take",
                         choices=PLANNERS)
    budget: float = param(1.0, "-", "planning effort for one path, counted in work", positive=True)
    rod_limit: float = param(15.0, "-", "largest aspect ratio L/d pushed as a rigid rod", positive=True)
    min_confidence: float = param(0.5, "-", "objects identified with less confidence are never assigned",
                                  lo=0.0, hi=1.0)
    seed: int = param(0, "-", "seed of OMPL's sampler", nonnegative=True)
    rod_swing: float = param(45.0, "deg", "largest rotation of one rod push", positive=True, hi=60.0)
    rod_push_point: float = param(0.2, "-", "push point of rod pushes, fraction of the length from the "
                                  "pushed end", lo=0.0, hi=0.3)
    rod_direct: str = param("always", "", "a rod's direct search first: always, or only when its straight "
                            "way is clear (faster first plans, more pushes)", choices=("always", "clear"))
    rod_search: str = param("greedy", "", "a rod's lattice search: greedy, or refine (the direct search's way searched "
                            "again less greedily for fewer pushes, where the slot is not between fixed things)",
                            choices=("greedy", "refine"))
    align: str = param("rigid", "", "registration of a layout with marks: rigid, similarity (scale too) or none",
                       choices=ALIGNS)

    def __post_init__(self) -> None:
        validate(self)

    @property
    def clearance(self) -> float:
        """What every path keeps clear beyond the footprints: tip radius + margin."""
        return self.tip_radius + self.margin
