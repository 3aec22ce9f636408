"""The receding-horizon finish of a rod (issue 14): the closed-form pushes it optimises are
the pivot model's, and it lands a rod whose error lies along its own axis (the direction
the library of small swings needed a dozen pushes or more for) in a few pushes."""

from __future__ import annotations

import math

import pytest
import shapely

from nanoasm.bodies import Body
from nanoasm.planner.freespace import FreeSpace
from nanoasm.planner.options import PlanOptions
from nanoasm.planner.rod_horizon import pivot_place, plan_swings
from nanoasm.planner.rods import RodController, push_primitive, simulate_push

L, D = 539.0, 50.0
OPTS = PlanOptions()


@pytest.mark.parametrize("end", [-1, 1])
@pytest.mark.parametrize("side", [-1, 1])
@pytest.mark.parametrize("offset", [0.0, 0.04])
def test_a_push_is_a_turn_about_the_pivot_place(end, side, offset):
    """The full model's pose after a primitive push equals the closed form the horizon
    optimises (a rotation about ``pivot_place``) to a fraction of a nm."""
    rod = Body("r", "rod", (100.0, -50.0), D, 33.0, L)
    t0, t1 = push_primitive(rod, end, side, 15.0, OPTS)
    after = simulate_push(rod, t0, t1, OPTS.tip_radius, pivot_offset=offset)
    p, th = pivot_place(rod, end, OPTS.rod_push_point, offset), math.radians(rod.angle)
    phi = math.radians(after.angle - rod.angle)
    x = rod.at[0] + p * (math.cos(th) - math.cos(th + phi))
    y = rod.at[1] + p * (math.sin(th) - math.sin(th + phi))
    assert math.dist((x, y), after.at) < 0.5
    assert 14.0 < abs(after.angle - rod.angle) < 16.5


def _land(rod: Body, goal: Body, pos_tol: float, ang_tol: float, most: int = 12) -> tuple[int, Body]:
    """Pushes the horizon makes (each by the full model) until the rod is in the slot."""
    n = 0
    while n < most:
        if math.dist(rod.at, goal.at) <= pos_tol and abs(math.remainder(rod.angle - goal.angle, 180)) <= ang_tol:
            return n, rod
        (_, plan), *_ = plan_swings(rod, goal, push_point=OPTS.rod_push_point, max_swing=OPTS.rod_swing,
                                    pos_tol=pos_tol, ang_tol=ang_tol)
        for end, swing in plan:
            for side in (1, -1):
                t0, t1 = push_primitive(rod, end, side, abs(swing), OPTS)
                after = simulate_push(rod, t0, t1, OPTS.tip_radius)
                if (after.angle - rod.angle) * swing > 0:
                    rod = after
                    break
            n += 1
    return n, rod


@pytest.mark.parametrize("start", [(1955.0, 2000.0, 180.0), (1955.0, 2038.0, 185.5), (2040.0, 1990.0, 172.0),
                                   (2000.0, 2000.0, 170.0)])
def test_the_horizon_lands_a_rod_in_a_few_pushes(start):
    """Errors along the axis (45 nm), across and in angle: in the slot (6 nm, 0.9°) within
    eight pushes (the greedy choice among small swings took 17 from a pose like the second
    in one traced run, rods seed 1)."""
    goal = Body("g", "rod", (2000.0, 2000.0), D, 180.0, L)
    n, rod = _land(Body("r", "rod", start[:2], D, start[2], L), goal, 6.0, 0.9)
    assert math.dist(rod.at, goal.at) <= 6.0 and abs(math.remainder(rod.angle - 180.0, 180)) <= 0.9
    assert n <= 8


def test_the_controller_finishes_by_the_horizon_and_keeps_clear():
    """In free space the controller's finish is the horizon's: in the slot within eight
    pushes. With an electrode 60 nm beside the slot, every plan of the horizon (it knows no
    obstacles yet) swings an end into it, so the finish falls back to the library of small
    swings: still in the slot, and no pose or tip of it touches the electrode (11 pushes
    when this was written)."""
    goal = Body("g", "rod", (2000.0, 2000.0), D, 0.0, L)
    start = Body("r", "rod", (1955.0, 1985.0), D, 4.0, L)
    free = FreeSpace((4000.0, 4000.0), [], {"r": start}, clearance=OPTS.clearance)
    pushes, end, ok = RodController(free, OPTS, 6.0, 0.9).pushes(start, goal)
    assert ok and len(pushes) <= 8 and math.dist(end.at, goal.at) <= 6.0
    electrode = shapely.box(1500.0, 2000.0 + D / 2 + 60.0, 2500.0, 2400.0)
    free = FreeSpace((4000.0, 4000.0), [(electrode, 0.0)], {"r": start}, clearance=OPTS.clearance)
    pushes, end, ok = RodController(free, OPTS, 6.0, 0.9).pushes(start, goal)
    assert ok and math.dist(end.at, goal.at) <= 6.0
    for p in pushes:
        assert p.pose.geometry().distance(electrode) > p.pose.radius
        assert shapely.Point(p.tip_path[0]).distance(electrode) > OPTS.tip_radius


@pytest.mark.parametrize("mode", ["always", "clear"])
def test_the_direct_search_comes_first_always_or_only_where_the_straight_way_is_clear(mode, monkeypatch):
    """A wall between the rod and its slot blocks the straight sweep: with ``always`` the
    first lattice search heads for the slot itself, with ``clear`` for the first waypoint
    of an SE(2) path round the wall. In free space both head for the slot."""
    opts = PlanOptions(rod_direct=mode)
    start = Body("r", "rod", (1000.0, 2000.0), D, 90.0, L)
    goal = Body("g", "rod", (3000.0, 2000.0), D, 90.0, L)
    wall = shapely.box(1950.0, 1400.0, 2050.0, 2600.0)
    real, aims = RodController._search, []

    def search(self, rod, aim, *rest):
        aims.append(aim.at)
        return real(self, rod, aim, *rest)
    monkeypatch.setattr(RodController, "_search", search)
    for fixed, blocked in (([], False), ([(wall, 0.0)], True)):
        aims.clear()
        free = FreeSpace((4000.0, 4000.0), fixed, {"r": start}, clearance=opts.clearance)
        RodController(free, opts, 6.0, 0.9).pushes(start, goal)
        assert aims, "no lattice search ran"
        assert (aims[0] == goal.at) == (mode == "always" or not blocked)
