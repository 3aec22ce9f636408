"""The planner's one OMPL setup: budgets counted in work, planners chosen by name for
both the particle and the rod planner, plans that do not depend on the machine's load."""

from __future__ import annotations

import logging
import time

import pytest
import shapely

from nanoasm.bodies import Body
from nanoasm.planner import PlanOptions
from nanoasm.planner import ompl_setup
from nanoasm.planner.freespace import FreeSpace
from nanoasm.planner.ompl_setup import Budget
from nanoasm.planner.paths import Mover, ompl_path
from nanoasm.planner.rods import se2_waypoints


def test_a_budget_counts_its_asks_and_stops_at_zero():
    b = Budget(3, 60.0, "test")
    assert [b() for _ in range(5)] == [False, False, False, True, True]
    assert b.used == 3 and not b.guard_fired


def test_the_wall_clock_guard_stops_a_search_and_says_so(caplog):
    b = Budget(10 ** 9, 0.0, "a slow search")
    time.sleep(0.001)
    with caplog.at_level(logging.WARNING, logger="nanoasm.planner"):
        assert b() is True
        assert b() is True
    assert b.guard_fired
    assert sum("a slow search" in r.getMessage() for r in caplog.records) == 1   # logged once


def test_a_budget_scales_with_the_options():
    small = Budget.of(PlanOptions(budget=0.5), 1000, "x")
    large = Budget.of(PlanOptions(budget=2.0), 1000, "x", share=3)
    assert (small.left, large.left) == (500, 6000)


def _space():
    """A wall across the area with one gap near the top: no straight line gets past."""
    wall = shapely.box(900.0, 0.0, 1100.0, 1600.0)
    return FreeSpace((2000.0, 2000.0), [(wall, 0.0)], {}, 30.0)


@pytest.mark.parametrize("planner", ["rrtconnect", "kpiece", "rrtstar"])
def test_a_detour_is_the_same_for_the_same_seed_under_load_or_not(planner):
    space = _space()
    mover = Mover(space, "p", 40.0)
    opts = PlanOptions(planner=planner, budget=0.05, seed=3)
    first = ompl_path(mover, (300.0, 300.0), (1700.0, 300.0), opts)
    busy = [sum(range(20000)) for _ in range(10)]      # the machine does other work between
    again = ompl_path(mover, (300.0, 300.0), (1700.0, 300.0), opts)
    assert busy and first is not None and first == again
    assert len(first) > 2                              # around the wall, not through it


def test_the_rod_planner_honours_the_planner_option():
    space = _space()
    rod = Body("r", "rod", (400.0, 400.0), 60.0, 90.0, 500.0)
    goal = Body("r", "rod", (1600.0, 400.0), 60.0, 90.0, 500.0)
    seen = []
    real = ompl_setup.solve

    def spy(*args, **kw):
        seen.append((kw.get("planner") or args[3].planner))
        return real(*args, **kw)

    ompl_setup.solve = spy
    try:
        path = se2_waypoints(space, rod, goal, PlanOptions(planner="kpiece", budget=0.2, seed=1))
    finally:
        ompl_setup.solve = real
    assert seen and set(seen) == {"kpiece"}
    assert path is not None and path[-1].at == pytest.approx(goal.at, abs=1e-6)
