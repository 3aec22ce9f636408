"""Faults of the simulated AFM (``[faults]``), each observable when its probability is 1."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from nanoasm.world.params import FaultParams
from nanoasm.world.sim import draw_push_faults

LOST_DISTANCE = (FaultParams().lost_min, FaultParams().lost_max)
SLIP_AFTER = (FaultParams().slip_after_min, FaultParams().slip_after_max)
from nanoasm.instrument import InstrumentConfig
from nanoasm.world.params import FaultParams
from simkit import EXACT, particle, push, rod, world


def _faulty(**kw):
    return dataclasses.replace(EXACT, faults=FaultParams(**kw))


def test_faults_are_off_by_default():
    f = draw_push_faults(FaultParams(), 35.0, np.random.default_rng(0))
    assert not f.any


@pytest.mark.parametrize("dac_bits, rise", [(16, 0.15), (20, 0.8)])
def test_stuck_object_stays_while_the_force_rises_past_a_limit_then_the_tip_slips(dac_bits, rise):
    # the lever's lateral stiffness (k_l K_l/h / C1 = 29 nN/nm) takes the force from the
    # push's 14 nN to the 64 nN that lifts the tip within ~2 nm: two 16-bit DAC codes
    fine = InstrumentConfig(dac_bits=dac_bits)
    params = dataclasses.replace(_faulty(stuck_object=1.0), scanner=fine)
    sim = world([particle((2000, 2000))], params=params)
    block, _ = push(sim, (2000, 1800), (2000, 2300))               # along y: S_l sees the force
    ok = world([particle((2000, 2000))], params=dataclasses.replace(EXACT, scanner=fine))
    normal, _ = push(ok, (2000, 1800), (2000, 2300))
    assert sim.truth() == sim.scene.objects
    base = np.median(normal.s_l[-1000:-10])                          # a normal push's level
    assert block.s_l.max() > base + rise
    assert sim.diagnostics()["slips"] == 1
    assert np.median(block.s_l[-600:-10]) < base - 0.2               # collapsed: friction only


def test_tip_slip_leaves_the_object_part_way():
    sim = world([particle((2000, 2000))], params=_faulty(tip_slip=1.0))
    push(sim, (1800, 2000), (2400, 2000))
    moved = sim.truth()[0].at[0] - 2000
    rc = 35.0
    assert SLIP_AFTER[0] * rc - 2 < moved < SLIP_AFTER[1] * rc + 2    # the full push moves it 435 nm
    assert sim.diagnostics()["slips"] == 1


def test_lost_object_jumps_far_away():
    for obj in (particle((2000, 2000)), rod((2000, 2100), 0.0, 400.0, id="p1")):
        sim = world([obj], params=_faulty(lost_object=1.0))
        push(sim, (1950, 1800) if obj.kind == "rod" else (1800, 2000),
             (1950, 2300) if obj.kind == "rod" else (2400, 2000))
        jump = math.dist(sim.truth()[0].at, obj.at)
        assert LOST_DISTANCE[0] <= jump <= LOST_DISTANCE[1] + 1
        assert sim.truth()[0].angle == obj.angle


def test_blunted_tip_broadens_scans():
    sim = world([particle((2000, 2000), d=50)], params=_faulty(tip_blunting=1.0))
    before = sim.full_scan(256, (1800.0, 1800.0, 2200.0, 2200.0))
    push(sim, (2000, 1900), (2000, 1975))                           # a short push: one blunting
    step = sim.params.faults.blunting_step
    assert sim.diagnostics()["tip_radius"] == pytest.approx(sim.params.tip.radius + step)
    (p,) = sim.truth()
    region = (p.at[0] - 200, p.at[1] - 200, p.at[0] + 200, p.at[1] + 200)
    after = sim.full_scan(256, region)
    assert _area_above(after, 25.0) > 1.1 * _area_above(before, 25.0)


def _area_above(image, level):
    return np.count_nonzero(image.height > level) * image.pixel_size ** 2


def test_fault_draws_do_not_shift_each_other():
    a = draw_push_faults(FaultParams(stuck_object=1.0), 30.0, np.random.default_rng(3))
    b = draw_push_faults(FaultParams(), 30.0, np.random.default_rng(3))
    c = draw_push_faults(FaultParams(lost_object=1.0), 30.0, np.random.default_rng(3))
    assert a.stuck and not b.stuck and c.lost and c.slip_after == b.slip_after == math.inf
    assert math.hypot(*c.jump) >= LOST_DISTANCE[0]
