"""The simulated tip force while it pushes: the object's contact force along the tip–object
contact normal plus friction against the motion (issue 13), so an object pushed
off-centre shows in the signals on its side, as it would on a real lever."""

from __future__ import annotations

import math

import numpy as np
import pytest
from simkit import particle, push, world

from nanoasm.world.cantilever import to_afm

R, TIP = 45.0, 10.0


def _pushed(direction, offset: float):
    """A 90 nm particle pushed 600 nm along ``direction`` (AFM frame) with the tip's line
    ``offset`` nm to the left of its centre; its own turn set to 0. Returns the compensated
    signals' change from the tip's sliding before contact to mid-push, and the sim."""
    sim = world([particle((2000.0, 2000.0), d=2 * R)])
    sim._world.table.path_error[0] = 0.0
    u = np.asarray(direction, float) / np.linalg.norm(direction)
    v = np.array([-u[1], u[0]])
    start = np.array([2000.0, 2000.0]) - u * (R + TIP + 60.0) + v * offset
    block, codes = push(sim, start, start + 600.0 * u)
    contact = np.flatnonzero(sim.config.codes_to_nm(codes)[:, 2] <= 0.0)
    before = contact[len(contact) // 20: len(contact) // 10]       # sliding, not yet touching
    mid = contact[len(contact) // 2: 3 * len(contact) // 4]
    return (block.s_n[mid].mean() - block.s_n[before].mean(),
            block.s_l[mid].mean() - block.s_l[before].mean()), sim


@pytest.mark.parametrize("direction", [(1.0, 0.0), (0.0, 1.0), (0.6, 0.8), (-0.8, 0.6)])
def test_an_off_centre_push_twists_the_lever_to_the_particles_side(direction):
    """The lateral force's part across the push, from (S_n, S_l) by eq. 3.5, 3.6, 3.9 and
    R(ψ)⁻¹, is the contact force times sin α, α the contact normal's angle from the motion;
    on the particle's side, growing with the offset, zero when centred."""
    across = {}
    for offset in (-10.0, 0.0, 10.0):
        (dsn, dsl), sim = _pushed(direction, offset)
        lv = sim._model.lever
        # (F_x, F_y) in the cantilever frame from the signals' change (F_z unchanged, α of S_n small)
        fy = lv.lateral_gain * (dsl - lv.crosstalk * dsn)
        fx = lv.spring_constant * lv.normal_gain * dsn * lv.lever_length / lv.tip_height
        f_afm = to_afm(np.array([[fx, fy]]), sim.params.scanner.scan_angle)[0]
        u = np.asarray(direction, float) / np.linalg.norm(direction)
        across[offset] = float(f_afm @ np.array([-u[1], u[0]]))
        along = float(f_afm @ u)
    assert along < -10.0                                     # the contact force holds the tip back
    assert abs(across[0.0]) < 1.0
    # the particle sits to the tip's right when the tip's line is left of its centre: the
    # force on the tip points away from the particle, so to the left (+) for offset +10
    assert across[10.0] > 2.0 and across[-10.0] < -2.0
    alpha = math.asin(10.0 / (R + TIP))
    assert across[10.0] == pytest.approx(-along * math.tan(alpha), rel=0.5)


def test_a_centred_push_along_the_motion_leaves_the_force_on_the_line():
    (dsn, dsl), sim = _pushed((1.0, 0.0), 0.0)
    (b,) = sim.truth()
    assert abs(b.at[1] - 2000.0) < 1.0 and b.at[0] - 2000.0 > 500.0
