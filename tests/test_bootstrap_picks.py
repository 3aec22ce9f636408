"""The drift bootstrap's picks (executor/bootstrap_picks.py): each stretch of the full
scan's rows gives its roomiest particle or corner, latest first."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from nanoasm.executor.belief import Belief, Seen
from nanoasm.executor.bootstrap_picks import ROOMY_ENOUGH, TRIES, Picks, gaps
from nanoasm.world.environment import EnvObject, EnvObstacle, Environment

NO_FEATURES = SimpleNamespace(features={}, seen={})


def _belief(points, obstacles=()) -> Belief:
    objs = tuple(EnvObject(f"o{i}", "particle", (float(x), float(y)), 80.0) for i, (x, y) in enumerate(points))
    b = Belief(Environment((10000.0, 10000.0), objs, tuple(obstacles), "test"), 0.0)
    for o in objs:                              # seen on the row at its y, a second per 10 nm
        b.seen[o.id] = Seen(o.at[1] / 10.0, np.eye(2) * 4.0)
    return b


def test_each_stretch_of_rows_gives_its_roomiest_particle_latest_first():
    """Two stretches of rows: in each, the particles crowd in pairs (gap 20 nm) but one,
    which is picked though an even spread would take the crowded first and last rows'."""
    pts = [(1000.0, 100.0), (1100.0, 100.0), (5000.0, 2000.0), (1000.0, 3000.0),
           (1000.0, 6000.0), (8000.0, 8000.0), (1000.0, 9000.0), (1100.0, 9000.0)]
    b = _belief(pts)
    picks = Picks(b, NO_FEATURES, 2)
    order = []
    for c in picks:
        order.append(c[1])
        picks.found()
    assert order[:2] == ["o5", "o2"]
    assert sorted(order) == [f"o{i}" for i in range(8)]
    g = gaps(b, NO_FEATURES, [("object", "o0", 10.0)])
    assert abs(g[0] - 20.0) < 1e-9


def test_an_obstacle_crowds_a_particle_too():
    wall = EnvObstacle(((0.0, 0.0), (1000.0, 0.0), (1000.0, 1000.0), (0.0, 1000.0)), 30.0)
    b = _belief([(1100.0, 500.0), (6000.0, 500.0)], [wall])
    g = gaps(b, NO_FEATURES, [("object", "o0", 50.0), ("object", "o1", 50.0)])
    assert abs(g[0] - 60.0) < 1e-9 and g[1] > 4000.0


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.floats(0, 9000), st.floats(0, 9000)), min_size=2, max_size=30, unique=True))
def test_gaps_are_the_nearest_footprints_distance(points):
    """The gap is the least distance between footprints (80 nm particles) over every other
    particle, where it is below what counts (the search stops beyond)."""
    b = _belief(points)
    cands = [("object", f"o{i}", 0.0) for i in range(len(points))]
    g = gaps(b, NO_FEATURES, cands)
    P = np.asarray(points)
    d = np.hypot(*(P[:, None, :] - P[None, :, :]).transpose(2, 0, 1)) - 80.0
    np.fill_diagonal(d, np.inf)
    want = d.min(axis=1)
    near = want < ROOMY_ENOUGH
    np.testing.assert_allclose(g[near], want[near], atol=1e-6)
    assert np.all(g[~near] >= ROOMY_ENOUGH - 1e-6)


def test_a_pick_not_found_or_left_out_is_replaced_from_its_own_stretch():
    """Four stretches of two rows each: the first picks come one from each, latest first;
    a pick not found is replaced from its stretch (a tear of the scan put the early rows'
    picks out of reach, and replacements from the latest rows left none before it to
    show the tear), until it has failed TRIES times in a row; a pick left out after it
    was found is replaced from its stretch too."""
    pts = [(500.0 + 1500.0 * (i % 2), 100.0 + 1000.0 * i) for i in range(12)]
    picks = Picks(_belief(pts), NO_FEATURES, 4)
    it = iter(picks)
    got = []
    for _ in range(4):
        got.append(next(it)[1])
        picks.found()
    assert got == ["o11", "o7", "o4", "o0"]        # roomy alike: nearest where an even spread picks
    picks.left_out("o7")
    assert next(it)[1] == "o8"                     # o7's stretch: rows 6-8
    fresh = Picks(_belief(pts), NO_FEATURES, 4)
    it = iter(fresh)
    assert TRIES == 3
    tries = [next(it)[1] for _ in range(TRIES + 1)]   # none found
    assert tries == ["o11", "o10", "o9", "o7"]
    fresh.found()                                  # o7: the failed stretch waits for the others
    assert next(it)[1] == "o4"
    fresh.found()
    assert next(it)[1] == "o0"
    fresh.found()
    assert next(it)[1] == "o8"                     # a second round, not back to o11's stretch


def test_without_particles_or_corners_the_edges_come_latest_first():
    marks = SimpleNamespace(features={"e1": SimpleNamespace(kind="edge"), "e2": SimpleNamespace(kind="edge")},
                            seen={"e1": [10.0], "e2": [20.0]})
    assert [c[1] for c in Picks(_belief([]), marks, 4)] == ["e2", "e1"]


def test_one_more_of_the_latest_rows_comes_from_their_stretch():
    """A jump taken from a reference's time, with the references scanned again latest row
    first, fits as well as a tear between two of their rows: the bootstrap scans one more
    of the latest rows' stretch to tell them apart (``Picks.latest``; the whole case in
    ``test_relocalise.py``)."""
    pts = [(500.0 + 1500.0 * (i % 2), 100.0 + 1000.0 * i) for i in range(12)]
    picks = Picks(_belief(pts), NO_FEATURES, 4)
    it = iter(picks)
    for _ in range(4):
        next(it)
        picks.found()
    more = picks.latest()
    assert next(more)[1] == "o10"
    picks.found()
    assert picks.have == [2, 1, 1, 1]
    assert [c[1] for c in more] == ["o9"]          # what is left of the stretch
    assert list(picks.latest()) == []
