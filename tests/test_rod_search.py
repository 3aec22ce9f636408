"""The rod's lattice search (weighted A*): the greedy weight finds a way; with
``rod_search = "refine"``, in open space, that way is searched again with the less greedy
``SEARCH_WEIGHT`` for fewer pushes; toward a slot enclosed by fixed things (a gap between
electrodes) it is not, nor with the default ``greedy`` (bench/RESULTS_rods.md, 2026-12-07)."""

from __future__ import annotations

import math
import random

import pytest
import shapely

from nanoasm.bodies import Body
from nanoasm.planner import rods
from nanoasm.planner.freespace import FreeSpace
from nanoasm.planner.options import PlanOptions
from nanoasm.planner.rods import RodController

L, D = 1000.0, 60.0
OPTS = PlanOptions()
REFINE = PlanOptions(rod_search="refine")


def _cases(n: int, seed: int) -> list[tuple[Body, Body]]:
    """Rods 0.9-1.5 µm from their slots, any bearing and angles (open space)."""
    rng = random.Random(seed)
    out = []
    for _ in range(n):
        d, bearing = rng.uniform(900.0, 1500.0), math.radians(rng.uniform(0.0, 360.0))
        start = Body("r", "rod", (3000.0 + d * math.cos(bearing), 3000.0 + d * math.sin(bearing)), D,
                     rng.uniform(0.0, 180.0), L)
        out.append((start, Body("g", "rod", (3000.0, 3000.0), D, rng.uniform(0.0, 180.0), L)))
    return out


def _plan(start: Body, goal: Body, fixed: list, opts: PlanOptions = REFINE
          ) -> tuple[list, Body, bool, RodController]:
    free = FreeSpace((6000.0, 6000.0), fixed, {"r": start}, clearance=opts.clearance)
    ctrl = RodController(free, opts, 6.0, 0.9)
    return (*ctrl.pushes(start, goal), ctrl)


def test_the_less_greedy_search_finds_shorter_ways_and_spends_none_of_the_allowance(monkeypatch):
    """Eight rods in open space, each searched to within 50 nm and 10° of its slot: the
    greedy way alone, searched again with the greedy weight, and with ``SEARCH_WEIGHT``.
    No way of the last is longer than the greedy way, together they are the fewest (60,
    62 and 65 pushes when this was written), and the allowance the phase counts is the
    greedy search's alone."""
    ours = rods.SEARCH_WEIGHT
    found: dict[str, list[tuple[int, int]]] = {}
    for name, refine, weight in (("greedy", False, ours), ("again", True, rods.GREEDY_WEIGHT),
                                 ("ours", True, ours)):
        monkeypatch.setattr(rods, "SEARCH_WEIGHT", weight)
        found[name] = []
        for start, goal in _cases(8, 3):
            free = FreeSpace((6000.0, 6000.0), [], {"r": start}, clearance=OPTS.clearance)
            ctrl = RodController(free, OPTS, 6.0, 0.9)
            ctrl.allowance = rods.Budget(10_000, math.inf, "test")
            way = ctrl._search(start, goal, 50.0, 10.0, refine)
            found[name].append((len(way), ctrl.allowance.used))
    assert all(a[1] == b[1] > 0 for a, b in zip(found["ours"], found["greedy"]))
    assert all(a[0] <= b[0] for a, b in zip(found["ours"], found["greedy"]))
    total = {k: sum(n for n, _ in v) for k, v in found.items()}
    assert total["ours"] < total["again"] < total["greedy"]


def _refined(monkeypatch) -> list[int]:
    """Record the pushes bound of every search for a shorter way."""
    calls: list[int] = []
    real = RodController._astar

    def astar(self, *a, within=None, **k):
        if within is not None:
            calls.append(within)
        return real(self, *a, within=within, **k)
    monkeypatch.setattr(RodController, "_astar", astar)
    return calls


@pytest.mark.parametrize("opts", [REFINE, OPTS])
def test_open_space_plans_reach_their_slots(opts, monkeypatch):
    """The whole plans of the same eight rods (the search, then the last pushes) reach
    their slots; the ways are searched again with ``refine`` only."""
    calls = _refined(monkeypatch)
    for start, goal in _cases(8, 3):
        calls.clear()
        pushes, end, ok, ctrl = _plan(start, goal, [], opts)
        assert ok and math.dist(end.at, goal.at) <= 6.0 and len(pushes) <= 12
        assert bool(calls) == (opts is REFINE)


@pytest.mark.parametrize("gap", [1200.0, 3000.0])
def test_a_slot_between_electrodes_is_not_searched_again(gap, monkeypatch):
    """Two pads either side of a 1000 nm rod's slot along its axis: 1200 nm apart the slot
    has no room to line the rod up in and the greedy way stands; 3000 nm apart it has,
    and the way is searched again."""
    calls = _refined(monkeypatch)
    goal = Body("g", "rod", (3000.0, 3000.0), D, 0.0, L)
    start = Body("r", "rod", (3000.0, 1800.0), D, 30.0, L)
    pads = [(shapely.box(3000.0 + s * gap / 2, 2700.0, 3000.0 + s * (gap / 2 + 500.0), 3300.0), 0.0)
            for s in (-1, 1)]
    _plan(start, goal, pads)
    assert bool(calls) == (gap > 2000.0)


def test_legs_along_an_se2_path_are_not_searched_again(monkeypatch):
    """A wall between a rod and its slot, the direct search skipped (``rod_direct =
    "clear"``): the legs along the SE(2) path keep the greedy ways even with ``refine``
    (refined legs lost the bowtie's rod slot on three of ten seeds)."""
    calls = _refined(monkeypatch)
    legs: list[int] = []
    real = RodController._search

    def search(self, *a, **k):
        legs.append(1)
        return real(self, *a, **k)
    monkeypatch.setattr(RodController, "_search", search)
    opts = PlanOptions(rod_direct="clear", rod_search="refine")
    start = Body("r", "rod", (1000.0, 2000.0), 50.0, 90.0, 539.0)
    goal = Body("g", "rod", (3000.0, 2000.0), 50.0, 90.0, 539.0)
    wall = shapely.box(1950.0, 1400.0, 2050.0, 2600.0)
    free = FreeSpace((4000.0, 4000.0), [(wall, 0.0)], {"r": start}, clearance=opts.clearance)
    RodController(free, opts, 6.0, 0.9).pushes(start, goal)
    assert legs and not calls
