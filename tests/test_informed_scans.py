"""Scans chosen by what is uncertain (issue 16): one line that confirms an after-scan
before the next push of its object, a rod's and a particle's after-scan placed where the
push model puts them, and the mode switches the report now accounts for as such."""

from __future__ import annotations

import math

import numpy as np
import pytest

from simkit import SteadyDrift, particle, rod, world
from test_local_scan import angle_err, err, push_rod, scanner, sphere_profile

from nanoasm.executor.belief import Belief
from nanoasm.executor.context import RunContext
from nanoasm.executor.engine import RunEngine
from nanoasm.executor.estimators import NoDrift
from nanoasm.executor.guard_line import apex, guard
from nanoasm.executor.local_scan import particle_after, particle_after_predicted, rod_after, run_pattern
from nanoasm.executor.reference_choice import LineTiming
from nanoasm.executor.references import References
from nanoasm.executor.rod_predicted import rod_after_predicted
from nanoasm.executor.strategy import ExecOptions
from nanoasm.bodies import Body
from nanoasm.world.environment import EnvObject, Environment

TIP_RADIUS = 10.0


@pytest.mark.parametrize("off", [0.0, 10.0, 30.0, 54.9, 60.0])
def test_the_apex_read_off_centre_is_the_closed_form_sphere_profile(off):
    assert apex(45.0, TIP_RADIUS, off) == pytest.approx(float(sphere_profile(off, 0.0, 90.0, TIP_RADIUS)), abs=1e-9)
    assert apex(45.0, TIP_RADIUS, 0.0) == pytest.approx(90.0)


def _guard_run(true_body: Body, believed: EnvObject, heading=(1.0, 0.0)):
    """``guard`` of a believed pose against a simulated world holding ``true_body``:
    (why not, or None; the belief after; the lines scanned)."""
    sim = world([true_body])
    env = Environment((4000.0, 4000.0), (believed,), ())
    ctx = RunContext(sim.config, ExecOptions(strategy="local-scan"), NoDrift((0.0, 0.0), 0.0), Belief(env, 0.0),
                     References())
    why = RunEngine(sim, []).run(guard(ctx, believed.id, np.asarray(heading, float), TIP_RADIUS))
    return why, ctx.belief[believed.id], ctx.ledger.counts["local_scans"]


def test_a_particle_where_believed_is_confirmed_by_one_line_across_the_push_and_its_lateral_place_taken():
    why, b, scans = _guard_run(particle((2000, 2004), d=90.0), EnvObject("p1", "particle", (2005.0, 2000.0), 90.0))
    assert why is None and scans == 1
    assert b.at[1] == pytest.approx(2004.0, abs=1.0)        # across the push: measured
    assert b.at[0] == 2005.0                                  # along it: as believed


@pytest.mark.parametrize("along, across", [(30.0, 0.0), (300.0, 0.0), (0.0, 300.0)])
def test_a_particle_moved_since_its_after_scan_is_not_confirmed(along, across):
    """A drift jump along the push moves the line off its top (more than R/2 = 22.5 nm) or
    off it altogether; across the push, beyond the line's reach."""
    believed = EnvObject("p1", "particle", (2000.0, 2000.0), 90.0)
    why, b, _ = _guard_run(particle((2000 + along, 2000 + across), d=90.0), believed)
    assert why is not None
    assert b.at == believed.at                                # the belief left as it was


def test_a_rod_where_believed_is_confirmed_by_one_line_along_its_axis_and_its_axial_place_taken():
    truth = rod((2000 + 8 * math.cos(math.radians(30)), 2000 + 8 * math.sin(math.radians(30))), 30.0, 600.0, d=40.0)
    why, b, scans = _guard_run(truth, EnvObject("r1", "rod", (2000.0, 2000.0), 40.0, 30.0, 600.0))
    assert why is None and scans == 1
    assert math.dist(b.at, truth.at) < 1.5


@pytest.mark.parametrize("shift", [(0.0, 300.0), (300.0, 0.0), (0.0, 15.0), (-250.0, 0.0)])
def test_a_rod_moved_since_its_after_scan_is_not_confirmed(shift):
    """A drift jump moves a rod without turning it: across its axis the line runs off its
    crest (beyond about d/4, 10 nm) or misses it; along the axis by more than the line's
    reach it is cut by the line's end or lies beyond it."""
    believed = EnvObject("r1", "rod", (2000.0, 2000.0), 40.0, 0.0, 600.0)
    why, b, _ = _guard_run(rod((2000 + shift[0], 2000 + shift[1]), 0.0, 600.0, d=40.0), believed)
    assert why is not None and b.at == believed.at


def test_a_rod_with_a_particle_touching_its_end_is_not_confirmed():
    """The chord along the axis runs on into the particle: longer than the rod."""
    believed = EnvObject("r1", "rod", (2000.0, 2000.0), 40.0, 0.0, 600.0)
    sim_bodies = [rod((2000, 2000), 0.0, 600.0, d=40.0), particle((2000 + 300 + 20, 2000), d=40.0, id="p1")]
    sim = world(sim_bodies)
    env = Environment((4000.0, 4000.0), (believed,), ())
    ctx = RunContext(sim.config, ExecOptions(strategy="local-scan"), NoDrift((0.0, 0.0), 0.0), Belief(env, 0.0),
                     References())
    why = RunEngine(sim, []).run(guard(ctx, "r1", np.array([0.0, 1.0]), TIP_RADIUS))
    assert why is not None


@pytest.mark.parametrize("sigma", [4.0, 9.0, 14.0])
def test_a_rod_where_the_model_put_it_is_found_by_short_lines_first(sigma):
    """Where the prediction holds (within r_max / 2), the two short lines and V find the rod
    as well as the seed's pattern, with fewer nanometres of line."""
    rng = np.random.default_rng(int(sigma * 11))
    for _ in range(6):
        d, L, th0, c0, t, u, delta, c1, th1 = push_rod(rng, sigma)
        r_max = rng.uniform(10, 40)
        predicted = c1 + rng.uniform(-1, 1, 2) * r_max / 2
        predicted_angle = th1 + rng.uniform(-1, 1)
        bodies = [Body("r", "rod", tuple(c1), d, th1, L)]
        args = (c0, th0, L, d, t, u, delta, r_max)
        kw = dict(predicted=predicted, predicted_angle=predicted_angle)
        short = run_pattern(rod_after_predicted(*args, **kw), scanner(bodies, rng))
        seed = run_pattern(rod_after(*args, **kw), scanner(bodies, rng))
        assert short.found, short.reason
        assert err(short, c1) < 2.0 and angle_err(short.angle, th1) < 1.0
        assert short.length == pytest.approx(L, abs=2.0)
        roles = [o.line.role for o in short.lines]
        if roles[:2] == ["P0", "P1"] and "L'0" not in roles:
            assert short.total_length < seed.total_length
        else:                                   # a short line missed the crest: the seed's pattern ran
            assert "L'0" in roles or "L0" in roles


def test_a_rod_that_did_not_move_is_found_by_the_seeds_pattern_after_the_short_lines():
    """The tip slipped: the rod lies where it started, not where the model put it. The short
    lines miss it and the seed's pattern, run after them, finds it."""
    rng = np.random.default_rng(5)
    d, L, th0, c0, t, u, delta, c1, th1 = push_rod(rng, 9.0)
    result = run_pattern(rod_after_predicted(c0, th0, L, d, t, u, delta, 20.0, predicted=c1, predicted_angle=th1),
                         scanner([Body("r", "rod", tuple(c0), d, th0, L)], rng))
    assert result.found, result.reason
    assert err(result, c0) < 2.0 and angle_err(result.angle, th0) < 1.0
    roles = [o.line.role for o in result.lines]
    assert roles[0] == "P0" and ("L'0" in roles or "L0" in roles)


@pytest.mark.parametrize("length", [150.0, 800.0, 3000.0])
def test_a_particle_where_the_push_put_it_is_found_by_one_short_line_and_v(length):
    """Within r_max of O_a + Δ u, P'0 about it and V' find the particle as well as the
    seed's pattern, whose L'0 spans the whole push."""
    rng = np.random.default_rng(int(length))
    for _ in range(8):
        d, r_max = rng.uniform(30, 100), rng.uniform(10, 40)
        u = np.array([math.cos(a := rng.uniform(0, 2 * math.pi)), math.sin(a)])
        start = np.array([2000.0, 2000.0]) - u * length / 2
        truth = start + u * length + rng.uniform(-1, 1, 2) * r_max / 2
        bodies = [Body("p", "particle", tuple(truth), d)]
        args = (start, d, u, length, r_max)
        short = run_pattern(particle_after_predicted(*args), scanner(bodies, rng))
        seed = run_pattern(particle_after(*args), scanner(bodies, rng))
        assert short.found and seed.found, (short.reason, seed.reason)
        assert err(short, truth) < 1.5 and err(seed, truth) < 1.5
        assert [o.line.role for o in short.lines][:2] == ["P'0", "V'"]
        assert short.total_length < seed.total_length - length + 1e-6


def test_a_particle_the_tip_slipped_off_is_found_by_the_seeds_pattern_after_the_short_line():
    """The particle stayed at O_a (the tip slipped): P'0 about O_a + Δ u finds nothing and
    the seed's pattern, run after it, finds the particle where it started."""
    rng = np.random.default_rng(3)
    start, u = np.array([1500.0, 2000.0]), np.array([1.0, 0.0])
    result = run_pattern(particle_after_predicted(start, 90.0, u, 1000.0, 20.0),
                         scanner([Body("p", "particle", tuple(start), 90.0)], rng))
    assert result.found, result.reason
    assert err(result, start) < 1.5
    roles = [o.line.role for o in result.lines]
    assert roles[0] == "P'0" and roles[1] == "L'0"


def test_a_lines_time_beyond_its_learnt_cost_is_a_mode_switch():
    timing = LineTiming()
    for n in (100, 400, 200, 800):
        timing.observe(n, 0.2 + 0.001 * n)
    assert timing.switched(300, 0.5) == 0.0
    assert timing.switched(300, 2.5) == pytest.approx(2.0)
    timing.observe(300, 2.5)                       # and it is not learnt as a line's cost
    assert timing.seconds(1, 300) == pytest.approx(0.5)
    assert LineTiming().switched(300, 2.5) == 0.0  # nothing learnt yet: not told apart


def test_the_report_counts_the_switch_back_to_tapping_as_a_mode_switch():
    """Two mode switches a push cycle (into contact, back to tapping) at the simulator's 2 s:
    a rods-family run's mode switches are 4 s a push, and its local scans none of them
    (each push alone: pushes made together share their switches, tests/test_batching.py)."""
    from nanoasm.dryrun import dry_run
    from nanoasm.world.families import family_case

    scene, layout = family_case("rods", 1, 0.3)
    out = dry_run(scene, layout, seed=1, options=ExecOptions(contact_batch=1))
    t, n = out.report.instrument_time, out.report.counts.pushes
    switch = scene.params.timing.mode_switch
    assert t.mode_switch == pytest.approx(2 * switch * n, abs=switch)
    assert t.full_scan + t.local_scan + t.push + t.travel + t.mode_switch == pytest.approx(t.total, abs=1e-6)


def test_a_line_after_a_push_is_read_in_the_frame_of_when_it_was_scanned_after_the_mode_switch():
    """The first line after a push waits 2 s for the switch back to tapping: a sample drifting
    8 nm/s across it moves 16 nm meanwhile. The line's coordinate, less the drift estimate's
    shift since it was placed, is where the particle lies (1 nm)."""
    from dataclasses import replace as dc_replace

    from nanoasm.executor.push_legs import across
    from nanoasm.world.params import DriftParams
    from simkit import EXACT, push

    v = (0.0, 8.0)
    params = dc_replace(EXACT, drift=DriftParams(velocity=v, random_walk=0.0))
    sim = world([particle((2000.0, 2000.0), d=90.0)], params=params)
    push(sim, (500.0, 500.0), (700.0, 500.0))    # far away: the scanner is left in contact mode
    ctx = RunContext(sim.config, ExecOptions(strategy="local-scan"), SteadyDrift(v), Belief(
        Environment((4000.0, 4000.0), (EnvObject("p1", "particle", (2000.0, 2000.0), 90.0),), ()), 0.0),
        References())
    ctx.timing = LineTiming()
    for n in (100, 400, 200, 800):               # what the lines cost is learnt already
        ctx.timing.observe(n, sim.params.timing.scan_line_overhead + n / sim.config.sample_rate)
    t0 = sim.clock()
    got = RunEngine(sim, []).run(across(ctx, np.array([2000.0, 2000.0]), np.array([1.0, 0.0]), 90.0, 60.0))
    assert got is not None
    lateral, _ = got
    assert sim.clock() - t0 > params.timing.mode_switch
    assert abs(lateral) < 1.0, lateral
