"""Calibration experiments on the simulated AFM (seed 3.4): force curve and friction loop."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from nanoasm.world.params import CantileverParams
from simkit import EXACT, world


def test_force_curve_gives_the_normal_gain_crosstalk_and_adhesion():
    sim = world([])
    curve = sim.force_curve(n=800)
    c = sim.params.cantilever
    assert curve.normal_gain() == pytest.approx(c.K_n, rel=0.01)
    assert curve.crosstalk() == pytest.approx(c.alpha, abs=0.005)
    pull = sim.params.adhesion.pull_off_fraction * sim.params.adhesion.tip_substrate
    assert curve.pull_off_force(c.k) == pytest.approx(pull, rel=0.05)
    assert curve.tip_adhesion(c.k) == pytest.approx(sim.params.adhesion.tip_substrate, rel=0.05)
    assert sim.ledger()["push"] == pytest.approx(1600 / sim.config.sample_rate)
    assert sim.position()[2] >= sim.config.nm_to_codes(np.array([0, 0, sim.config.lift]))[2]


def test_force_curve_follows_a_different_lever():
    params = dataclasses.replace(EXACT, cantilever=CantileverParams(K_n=60.0, alpha=-0.05))
    curve = world([], params=params).force_curve(n=800)
    assert curve.normal_gain() == pytest.approx(60.0, rel=0.01)
    assert curve.crosstalk() == pytest.approx(-0.05, abs=0.005)


def test_friction_loop_reproduces_the_seed_slopes_and_calibration():
    sim = world([])
    c = sim.params.cantilever
    loop = sim.friction_loop(9.09)
    retrace, trace = loop.slopes(c.alpha)
    assert (retrace, trace) == pytest.approx((0.02, 0.07), abs=0.002)    # seed 3.4.3, Fig. 3.11
    cal = loop.calibrate(c.alpha, c.k, c.K_n)
    assert cal.lateral_gain == pytest.approx(c.lateral_gain, rel=0.01)
    assert cal.mu == pytest.approx(sim.params.friction.mu_ts, rel=0.03)


def test_friction_loop_calibrated_with_the_force_curve_crosstalk():
    sim = world([])
    c = sim.params.cantilever
    curve = sim.force_curve(n=2000)
    cal = sim.friction_loop(9.09, n=400).calibrate(curve.crosstalk(), c.k, curve.normal_gain())
    assert cal.lateral_gain == pytest.approx(c.lateral_gain, rel=0.06)
    assert cal.mu == pytest.approx(sim.params.friction.mu_ts, rel=0.1)


def test_calibration_inputs_are_checked():
    sim = world([])
    with pytest.raises(ValueError, match="tilt_deg"):
        sim.friction_loop(0.0)
    with pytest.raises(ValueError, match="loads"):
        sim.friction_loop(9.0, loads=[5.0])
    with pytest.raises(ValueError, match="force_curve"):
        sim.force_curve(z_top=-1.0)
