"""Drift references that cannot run out, each part alone: the choice by information per
second, the line timing learnt from the clock, quarantine and blame after pushes, the
Kalman estimator's re-validation and relocalisation triggers."""

from __future__ import annotations


import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from nanoasm.bodies import Body
from nanoasm.executor.belief import Belief
from nanoasm.executor.kalman_drift import Kalman
from nanoasm.executor.reference_choice import Candidate, LineTiming, best
from nanoasm.executor.references import QUARANTINE_REACH, References, swept_area
from nanoasm.executor.strategy import ExecOptions
from nanoasm.world.environment import EnvObject, Environment

OPTS = ExecOptions()


def _belief(*objs) -> Belief:
    return Belief(Environment((4000.0, 4000.0), tuple(objs), ()), 0.0)


def _p(oid, x, y, d=90.0) -> EnvObject:
    return EnvObject(oid, "particle", (x, y), d)


# -- information per second ------------------------------------------------------------------
def test_the_best_candidate_gives_most_information_per_second_ties_by_id():
    mk = lambda i, gain, sec: Candidate("object", i, np.eye(2), np.eye(2), sec, gain)  # noqa: E731
    assert best([mk("a", 10.0, 2.0), mk("b", 8.0, 1.0)]).id == "b"
    assert best([mk("b", 4.0, 1.0), mk("a", 8.0, 2.0)]).id == "b"      # equal rates: the larger id
    assert best([mk("a", 0.0, 1.0)]) is None and best([]) is None


def test_line_timing_learns_overhead_and_per_sample_time_and_ignores_mode_switches():
    lt = LineTiming()
    assert lt.seconds(1, 1000) == pytest.approx(0.2 + 1.0)          # defaults before any line
    for n in (100, 300, 200, 500, 400):
        lt.observe(n, 0.15 + 0.002 * n)
    lt.observe(300, 0.15 + 0.002 * 300 + 2.0)                        # a 2 s mode switch first
    over, per = lt.fit()
    assert over == pytest.approx(0.15) and per == pytest.approx(0.002)
    assert LineTiming.from_state(lt.state_dict()).fit() == pytest.approx((over, per))


# -- quarantine and blame --------------------------------------------------------------------
def test_a_push_quarantines_what_lies_within_reach_of_its_sweep_and_is_blamed_for_it():
    belief = _belief(_p("pushed", 1000, 1000), _p("near", 1500, 1000 + 45 + QUARANTINE_REACH - 10),
                     _p("far", 1500, 1600), _p("tip", 800, 1040))
    refs = References.of_scan(belief.objects.values(), belief.seen)
    start = belief["pushed"]
    end = Body("pushed", "particle", (2000.0, 1000.0), 90.0)
    area = swept_area("pushed", 50.0, [(900.0, 1000.0), (1950.0, 1000.0)], [start, end], tip_radius=10.0)
    hit = refs.pushed_near(area, belief)
    assert set(hit) == {"near", "tip"} and refs.quarantine == {"near": "pushed", "tip": "pushed"}
    assert not refs.usable("near", [], set()) and refs.is_reference("near", [], set())
    assert refs.usable("far", [], set())
    why = refs.moved("near", belief["near"].at, since=0.0)
    assert "push of pushed" in why and "near" in refs.gated and "near" not in refs.quarantine
    assert refs.moved("far", belief["far"].at, since=0.0) == "no push came within reach of it"
    assert refs.blame("tip", belief["tip"].at, since=60.0) is None      # pushes before its sighting
    back = References.from_state(refs.state_dict())
    assert back.quarantine == refs.quarantine and back.pushes == refs.pushes


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(0, 4000), st.floats(0, 4000), st.booleans(), st.floats(0, 180)),
                min_size=1, max_size=25),
       st.floats(200, 3800), st.floats(200, 3800), st.floats(-800, 800), st.floats(-800, 800))
def test_the_quarantine_hits_what_a_distance_to_every_object_would(objs, x, y, dx, dy):
    """The box test before the distance leaves out only what lies beyond reach: the same
    objects as the shapely distance to every one of them (rods reaching half their length)."""
    import shapely

    bodies = [EnvObject(f"o{k}", "rod", (ox, oy), 60.0, a, 700.0) if rod else _p(f"o{k}", ox, oy)
              for k, (ox, oy, rod, a) in enumerate(objs)]
    belief = _belief(_p("pushed", x, y), *bodies)
    refs = References.of_scan(belief.objects.values(), belief.seen)
    end = Body("pushed", "particle", (x + dx, y + dy), 90.0)
    area = swept_area("pushed", 5.0, [(x, y), (x + dx, y + dy)], [belief["pushed"], end], tip_radius=10.0)
    g = area.geometry()
    want = {b.id for b in bodies if shapely.distance(g, b.geometry()) - b.radius < QUARANTINE_REACH}
    assert set(refs.pushed_near(area, belief)) == want


def test_a_rods_sweep_covers_its_turn():
    a = Body("r", "rod", (1000.0, 1000.0), 80.0, 0.0, 600.0)
    b = Body("r", "rod", (1000.0, 1000.0), 80.0, 90.0, 600.0)
    area = swept_area("r", 1.0, [(1300.0, 950.0), (1300.0, 1100.0)], [a, b], tip_radius=10.0).geometry()
    assert area.contains(Body("x", "particle", (1180.0, 1180.0), 10.0).geometry())   # inside the sweep
    assert area.area > 0.6 * 600 * 600


# -- the Kalman estimator --------------------------------------------------------------------
def _kalman():
    objs = [_p("r1", 1000, 1000), _p("r2", 3000, 3000), _p("r3", 3000, 1000)]
    belief = _belief(*objs)
    est = Kalman((0.0, 0.0), 0.0, OPTS)
    est.full_scan_done()
    est.restart(0.0)
    return est, belief, References.of_scan(objs, belief.seen)


def test_a_quarantined_reference_is_checked_not_folded_and_revalidated_when_it_agrees():
    est, belief, refs = _kalman()
    refs.quarantine["r1"] = "p"
    x0 = est.filter.x
    assert est.measure("r1", (1001.0, 999.5), np.eye(2), 10.0, refs, [], set()) is True
    assert "r1" not in refs.quarantine and np.array_equal(est.filter.x, x0)   # nothing folded
    refs.quarantine["r2"] = "p"
    assert est.measure("r2", (3100.0, 3000.0), np.eye(2), 11.0, refs, [], set()) is False
    assert "r2" in refs.gated and "push" in refs.note("r2") or "no push" in refs.note("r2")


def test_rejections_in_a_row_call_for_relocalisation_and_an_acceptance_clears_them():
    est, belief, refs = _kalman()
    assert est.needs_relocalisation(10.0, OPTS) is None
    est.measure("r1", (1200.0, 1000.0), np.eye(2), 10.0, refs, [], set())
    assert est.trust.rejections == 1 and est.trust.streak_start == 10.0
    est.reject("e1", 12.0)
    why = est.needs_relocalisation(12.0, OPTS)
    assert why[0] == "rejections" and "r1, e1" in why[1]
    forgiven = est.relocalised(13.0, (200.0, 0.0), np.eye(2) * 4.0, 0.0, refs)
    assert forgiven == ["e1", "r1"] and "r1" not in refs.gated
    assert est.offset(13.0) == pytest.approx([200.0, 0.0], abs=0.1)
    assert est.sigma(13.0) < 2.5
    assert est.needs_relocalisation(13.0, OPTS) is None and est.trust.streak_start is None


def test_a_growing_sigma_and_a_long_pause_call_for_relocalisation_but_not_right_after_a_failure():
    est, _, _ = _kalman()                                 # the velocity known to its prior's 0.5 nm/s
    t = 200.0
    assert est.sigma(t) > OPTS.relocalise_sigma
    assert est.needs_relocalisation(t, OPTS)[0] == "sigma"
    est.relocalise_failed(t)
    assert est.needs_relocalisation(t + 10.0, OPTS) is None
    assert est.needs_relocalisation(t + OPTS.relocalise_pause, OPTS) is not None
    fresh, _, _ = _kalman()
    fresh.resumed(OPTS.relocalise_pause + 1.0)
    assert fresh.needs_relocalisation(0.0, OPTS)[0] == "pause"


def test_the_kalman_state_keeps_its_rejection_streak():
    est, _, refs = _kalman()
    est.reject("e2", 5.0)
    est.reject("r3", 6.0)
    from nanoasm.executor.estimators import estimator_from_state

    back = estimator_from_state(est.state_dict(), OPTS)
    assert back.trust.rejected == ["e2", "r3"] and back.trust.rejections == 2 and back.trust.streak_start == 5.0
