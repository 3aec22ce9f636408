"""The one OMPL setup of the planner: a planner chosen by name and a budget counted in work.

Both path planners go through :func:`solve`: the particle planner in the plane
(:mod:`nanoasm.planner.paths`) and the rod planner in SE(2) (:mod:`nanoasm.planner.rods`).
The space information (state space, validity checker, motion validator) is theirs; the
problem, the objective, the planner and the termination condition are set here.

A budget is counted in iterations, never in seconds, so the same seed gives the same
plan on a quiet workstation and on a loaded CI runner: OMPL asks its termination
condition once an iteration, and :class:`Budget` counts those asks. A wall-clock guard
(:data:`GUARD_SECONDS` per budget unit) stops only a pathological case, and it is
logged when it fires, since the plan then depends on the machine. The exception is the
threaded planners (PRM, PRM*: :data:`THREADED_SECONDS_PER_UNIT`), whose results depend
on thread timing anyway; the default, RRTConnect, is not one of them.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

from .options import PlanOptions

log = logging.getLogger("nanoasm.planner")

#: OMPL planner classes by the names the CLI accepts.
PLANNER_CLASSES = {
    "rrtconnect": "RRTConnect", "rrt": "RRT", "rrtstar": "RRTstar",
    "informedrrtstar": "InformedRRTstar", "bitstar": "BITstar", "prm": "PRM",
    "prmstar": "PRMstar", "fmt": "FMT", "kpiece": "KPIECE1", "bkpiece": "BKPIECE1",
    "lbkpiece": "LBKPIECE1",
}
#: Planners that build their roadmap in a thread of their own: a cost written in Python
#: would need the interpreter from that thread while solve() holds it (a deadlock), so
#: they optimise path length only.
THREADED = {"prm", "prmstar"}
#: Planners that keep improving a solution within their budget.
OPTIMIZING = {"rrtstar", "informedrrtstar", "bitstar", "prmstar", "fmt"}
#: Iterations of OMPL one unit of :attr:`PlanOptions.budget` buys (about a second of
#: RRTConnect on a path that cannot be found, among the bowtie example's objects).
ITERATIONS_PER_UNIT = 4000
#: Wall-clock seconds one budget unit buys a threaded planner (PRM, PRM*). Such a planner
#: grows its roadmap in a thread of its own, so its result depends on thread timing
#: whatever its budget, and a termination condition written in Python can deadlock with
#: that thread (seen here: PRM hung in 2 of 8 runs): it gets OMPL's own timed condition.
THREADED_SECONDS_PER_UNIT = 1.0
#: Wall-clock seconds per budget unit after which the guard stops a search anyway.
GUARD_SECONDS = 30.0


class Budget:
    """Work left to one search: ``iterations`` asks, with a logged wall-clock guard.

    Call it (OMPL's termination condition does, once an iteration) to learn whether the
    search must stop; :meth:`spend` counts work done elsewhere (the rod search's
    expansions) the same way.
    """

    def __init__(self, iterations: int, guard_seconds: float, what: str):
        self.left = int(iterations)
        self.used = 0
        self.what = what
        self.guard = guard_seconds
        self._deadline = time.perf_counter() + guard_seconds
        self.guard_fired = False

    @classmethod
    def of(cls, options: PlanOptions, per_unit: float, what: str, share: float = 1.0) -> Budget:
        """The budget ``share × options.budget`` units buy at ``per_unit`` a unit."""
        units = share * options.budget
        return cls(max(1, round(per_unit * units)), GUARD_SECONDS * units, what)

    def spend(self, n: int = 1) -> None:
        self.left -= n
        self.used += n

    def exhausted(self) -> bool:
        if self.left <= 0:
            return True
        if time.perf_counter() > self._deadline:
            if not self.guard_fired:
                self.guard_fired = True
                log.warning("%s: the wall-clock guard (%.0f s) stopped the search after %d "
                            "iterations; this plan depends on the machine's speed",
                            self.what, self.guard, self.used)
            return True
        return False

    def __call__(self) -> bool:
        """OMPL's termination condition: counts one iteration, True when the search stops."""
        done = self.exhausted()
        if not done:
            self.spend()
        return done


def solve(si: Any, start: Any, goal: Any, options: PlanOptions, *, what: str,
          objective: Callable[[Any], Any] | None = None, planner: str | None = None):
    """Plan from ``start`` to ``goal`` (allocated states of ``si``'s space) with the
    planner ``options.planner`` (or ``planner``) within ``options.budget``; returns the
    solution path (an OMPL ``PathGeometric``) or None if no exact solution was found.

    ``objective(si)`` gives an optimisation objective for optimising planners that may
    use one (a Python cost cannot run in a threaded planner); without it, or for other
    planners, the objective is path length and the search stops at the first solution.
    OMPL's sampler is seeded from ``options.seed``, so a plan is reproducible."""
    from ompl import base as ob, geometric as og, util as ou

    ou.setLogLevel(ou.LogLevel.LOG_NONE)
    name = planner or options.planner
    ss = og.SimpleSetup(si)
    ss.setStartAndGoalStates(start, goal)
    if objective is not None and name in OPTIMIZING and name not in THREADED:
        obj = objective(si)
    else:
        obj = ob.PathLengthOptimizationObjective(si)
        obj.setCostThreshold(ob.Cost(1e18))   # stop at the first solution
    ss.setOptimizationObjective(obj)
    ss.setPlanner(getattr(og, PLANNER_CLASSES[name])(si))
    if name in THREADED:
        condition = ob.timedPlannerTerminationCondition(THREADED_SECONDS_PER_UNIT * options.budget)
    else:
        budget = Budget.of(options, ITERATIONS_PER_UNIT, what)
        condition = ob.PlannerTerminationCondition(budget)
    status = ss.solve(condition)
    if status.getStatus() != ob.PlannerStatus.EXACT_SOLUTION:
        return None
    return ss.getSolutionPath()


def seed(options: PlanOptions, stream: int) -> None:
    """Seed OMPL's sampler for one search (``stream`` keeps the particle and the rod
    planners' sequences apart)."""
    from ompl import util as ou

    ou.RNG.setSeed(options.seed + stream)
