"""What surrounds a push in the simulated AFM: obstacles, neighbours (van der Waals), creep."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import shapely
from nanoasm.world.params import CreepParams, DriftParams, VdwParams
from nanoasm.world.scene import Obstacle
from simkit import EXACT, particle, path_codes, push, world

ELECTRODE = Obstacle(((2100.0, 1800.0), (2400.0, 1800.0), (2400.0, 2200.0), (2100.0, 2200.0)), 40.0)


def test_an_object_never_enters_an_obstacle():
    sim = world([particle((2000, 2000), d=50)], obstacles=[ELECTRODE])
    push(sim, (1850, 2000), (2300, 2000))
    (p,) = sim.truth()
    assert shapely.distance(ELECTRODE.geometry(), shapely.Point(p.at)) >= 25.0 - 1e-6
    assert p.at[0] > 2040                                   # it moved up to the electrode
    assert sim.diagnostics()["slips"] == 1                  # then the tip went over it


def test_an_object_against_an_obstacle_may_leave_it_but_not_go_deeper():
    """A device rod was left 4 nm into a pad's outline; every push then counted as entering
    the pad, even one taking the rod away, so the tip slipped over it three times and the
    run gave the rod up (device seed 9). An object already in an obstacle may leave it."""
    start = (2100.0 - 25.0 + 4.0, 2000.0)                   # 4 nm into the electrode's left side
    along = world([particle(start, d=50)], obstacles=[ELECTRODE])
    push(along, (start[0], 1940), (start[0], 2400))        # along the side, then past its corner
    (p,) = along.truth()
    assert p.at[1] > 2300 and along.diagnostics()["slips"] == 0
    deeper = world([particle(start, d=50)], obstacles=[ELECTRODE])
    push(deeper, (start[0] - 60, 2000), (start[0] + 100, 2000))
    (q,) = deeper.truth()
    assert q.at == pytest.approx(start) and deeper.diagnostics()["slips"] == 1


def test_the_tip_rides_up_an_obstacle_in_contact():
    sim = world([], obstacles=[ELECTRODE])
    block, _ = push(sim, (1900, 2000), (2300, 2000))
    c = sim.params.cantilever
    on_top = np.median(block.s_n[-300:-20])                 # pushing over the plateau
    assert on_top - (c.reflection_n + sim.config.preload / c.K_n) == pytest.approx(40.0 / c.K_n, abs=0.03)


def test_van_der_waals_error_only_near_other_objects():
    def final(amplitude, neighbour):
        params = dataclasses.replace(EXACT, vdw=VdwParams(range=20.0, amplitude=amplitude))
        objs = [particle((2000, 2000), id="a")] + ([particle((2600, 2000), id="b")] if neighbour else [])
        sim = world(objs, params=params, seed=4)
        push(sim, (1800, 2000), (2500, 2000))               # 'a' ends 15 nm short of 'b'
        return sim.truth()
    assert final(5.0, False) == final(0.0, False)           # alone: no error
    near, exact = final(5.0, True), final(0.0, True)
    assert near[0] != exact[0]
    assert math.dist(near[0].at, exact[0].at) < 30.0
    assert math.dist(near[0].at, near[1].at) >= 50.0 - 1e-6


def test_a_large_move_makes_the_sample_creep():
    def seen(amplitude):
        params = dataclasses.replace(EXACT, drift=DriftParams(velocity=(0.0, 0.0), random_walk=0.0),
                                     creep=CreepParams(amplitude=amplitude))
        sim = world([particle((2000, 45000), d=50)], area=(50000.0, 50000.0), params=params)
        t0 = sim.clock()
        sim.write(path_codes(sim, [(2000, 45000, sim.config.lift)]))   # from rest: a 43 µm step in -x
        t_end = sim.clock()
        sim.write(np.repeat(sim.position()[None, :], 100, axis=0))      # and a stop
        line = ((1700.0, 45000.0), (2300.0, 45000.0))
        t1 = sim.clock()
        first = _peak(sim.scan_line(*line, 601), 1700.0)
        sim.full_scan(64, (0.0, 0.0, 1000.0, 1000.0))                    # 64 s later
        t2 = sim.clock()
        return first, _peak(sim.scan_line(*line, 601), 1700.0), (t0, t_end, t1, t2)
    assert seen(0.0)[:2] == pytest.approx((2000.0, 2000.0), abs=1.5)
    first, second, (t0, t_end, t1, t2) = seen(0.001)
    # the piezo keeps extending along the step (-x): the sample appears moved by
    # γ Σ |s_i| log10(1 + (t - t_i)/τ), the step's pieces creeping from when they were
    # made, some time t_i between the travel's start and end (0.86 s at 50 µm/s)
    lo, hi = (43.0 * math.log10(1 + (t1 - t_end) / 0.1), 43.0 * math.log10(1 + (t1 - t0) / 0.1))
    assert lo + 10.0 < first - 2000.0 < hi          # well beyond the step made at its end: crept as it went
    gain = [43.0 * math.log10((0.1 + t2 - ti) / (0.1 + t1 - ti)) for ti in (t0, t_end)]
    assert gain[0] - 2.0 < second - first < gain[1] + 2.0


def _peak(z, x0):
    """Centre (nm) of the part of a 1 nm-pitch profile above half its maximum."""
    w = np.where(z > 0.5 * z.max(), z, 0.0)
    return x0 + float((w * np.arange(z.size)).sum() / w.sum())
