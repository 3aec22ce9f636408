"""The drift bootstrap's picks (executor/bootstrap_picks.py): each stretch of the full
scan's rows gives its roomiest particle or corner, latest first; a reference of the
first rows is added where the drift since the scan began is extrapolated."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nanoasm.executor.belief import Belief, Seen
from nanoasm.executor.bootstrap_picks import (EARLY_FLOOR, EARLY_GAIN, ROOMY_ENOUGH, TRIES, Picks, early_choice,
                                              gaps)
from nanoasm.executor.scan_drift import ScanDrift
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


def _late_rows_model(rows=(500.0, 560.0, 620.0, 680.0), now=810.0, seed=0) -> ScanDrift:
    """A scan model measured by references of the given rows (s) scanned again at ``now``
    and after (no moves: no creep), under a drift of 0.3, -0.1 nm/s."""
    rng = np.random.default_rng(seed)
    sd = ScanDrift(0.0, 0.5, 0.01, 0.1)
    sd.scan_ended([], 800.0)
    for k, tau0 in enumerate(rows):
        t = now + 5.0 * k
        for e in np.eye(2):
            sd.measure(e, float(e @ (np.array([0.3, -0.1]) * (t - tau0))) + rng.normal(0, 2.0), t, tau0, 20.0)
    return sd


def test_a_first_rows_reference_is_added_where_the_drift_since_the_start_is_extrapolated():
    """References of rows 500-680 s of an 800 s scan leave the drift since the scan began
    to the model's extrapolation (its steady change at the prior; σ 13.5 nm): a roomy
    particle of the first rows shrinks its σ the most and is chosen, one of the first rows
    without room for its lines is not, and a late row's alone is not worth it (σ to 13.4).
    Measured, the chosen one shrinks σ as expected, below :data:`EARLY_FLOOR` (4.9 nm): no
    more is chosen then."""
    sd = _late_rows_model()
    now = 840.0
    cov0 = sd.cov.copy()
    cands = [(("object", "late", 650.0), 650.0, 2000.0), (("object", "early", 60.0), 60.0, 2000.0),
             (("object", "crowded", 20.0), 20.0, 30.0)]
    assert early_choice(sd, now, cands[:1], 16.0) is None   # a late row's: too little
    before, after, pick = early_choice(sd, now, cands, 16.0)
    assert pick[1] == "early"
    assert np.array_equal(sd.cov, cov0)                  # tried on a copy
    assert before > EARLY_FLOOR and after <= EARLY_GAIN * before
    for e in np.eye(2):
        sd.measure(e, float(e @ (np.array([0.3, -0.1]) * (now - 60.0))), now, 60.0, 20.0)
    got = math.sqrt(np.linalg.eigvalsh(sd.offset_cov(now))[-1])
    assert got == pytest.approx(after, rel=1e-6)
    assert got < EARLY_FLOOR and early_choice(sd, now, cands, 16.0) is None


def test_no_early_reference_where_the_rows_are_spanned_or_none_has_room():
    """Seven references from the first rows to the last: σ 3.3 nm, below
    :data:`EARLY_FLOOR`; and a first-rows particle 40 nm from a neighbour is not taken
    for lines reaching 3σ (35 nm) and the margin."""
    sd = _late_rows_model(rows=(5.0, 100.0, 250.0, 400.0, 550.0, 700.0, 790.0))
    assert math.sqrt(np.linalg.eigvalsh(sd.offset_cov(840.0))[-1]) < EARLY_FLOOR
    cands = [(("object", "early", 5.0), 5.0, 2000.0)]
    assert early_choice(sd, 840.0, cands, 16.0) is None
    crowded = [(("object", "early", 60.0), 60.0, 40.0)]
    assert early_choice(_late_rows_model(), 840.0, crowded, 16.0) is None
