"""Tip–particle–substrate equilibrium (seed eq. 4.1–4.7) and the particle push step."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from nanoasm.world.particle_push import (
    PushOutcome,
    adhesion_from_area,
    adhesion_from_pull_off,
    effective_radius,
    jkr_contact_halfwidth,
    jkr_contact_radius,
    min_normal_force,
    particle_adhesions,
    particle_step,
    push_angle_deg,
    push_lateral_force,
    push_outcome,
    push_succeeds,
    rod_substrate_adhesion,
    theta_max_deg,
    tip_object_repulsion,
)


def equilibrium(theta_deg, mu, nu, f_os_a, f_ot_a, f_ts_a, rho=1.0):
    """Solve eq. 4.1, 4.2, 4.3, 4.5 as a linear system (F^f_ot = 0, F^r_ts = 0).

    Unknowns: F^r_ot, F^r_os, F^f_os, F_z. Returns them in that order.
    """
    c, s = math.cos(math.radians(theta_deg)), math.sin(math.radians(theta_deg))
    a = np.array([
        [c, 0.0, -1.0, 0.0],            # 4.1: F^r_ot cos θ − F^f_os = F^a_ot cos θ
        [s, -1.0, 0.0, 0.0],            # 4.2: F^r_os + F^a_ot sin θ = F^r_ot sin θ + F^a_os
        [-s, 0.0, 0.0, 1.0],            # 4.3: F_z + F^a_to sin θ + F^a_ts = F^r_to sin θ
        [0.0, -rho * mu, 1.0, 0.0],     # 4.5 (ρ = 1) / 4.14: F^f_os = ρ(μ F^r_os + ν F^a_os)
    ])
    b = np.array([f_ot_a * c, f_ot_a * s - f_os_a, -f_ot_a * s - f_ts_a, rho * nu * f_os_a])
    return np.linalg.solve(a, b)


@pytest.mark.parametrize("mu", [0.05, 0.3, 1.0, 3.0])
def test_theta_max_is_atan_inverse_mu(mu):
    assert theta_max_deg(mu) == pytest.approx(math.degrees(math.atan(1.0 / mu)), rel=1e-14)


def test_theta_max_without_friction_is_ninety():
    assert theta_max_deg(0.0) == 90.0


def test_push_angle_adds_twist_and_half_angle():
    assert push_angle_deg(0.4, 20.0) == pytest.approx(20.4)


@pytest.mark.parametrize("theta", [0.0, 10.0, 35.0, 60.0])
@pytest.mark.parametrize("mu,nu", [(0.1, 0.2), (0.5, 0.0), (0.0, 0.3)])
def test_min_normal_force_matches_equilibrium_solve(theta, mu, nu):
    f_os_a, f_ot_a, f_ts_a = 20.0, 3.0, 1.0
    if theta >= theta_max_deg(mu):
        pytest.skip("beyond θmax")
    f_ot_r, _, _, f_z = equilibrium(theta, mu, nu, f_os_a, f_ot_a, f_ts_a)
    assert min_normal_force(theta, mu, nu, f_os_a, f_ts_a) == pytest.approx(f_z, rel=1e-10, abs=1e-10)
    assert tip_object_repulsion(theta, mu, nu, f_os_a, f_ot_a) == pytest.approx(f_ot_r, rel=1e-10)


def test_lateral_force_without_tip_friction_equals_object_friction():
    theta, mu, nu, f_os_a, f_ot_a, f_ts_a = 25.0, 0.2, 0.1, 20.0, 3.0, 1.0
    _, _, f_os_f, f_z = equilibrium(theta, mu, nu, f_os_a, f_ot_a, f_ts_a)
    assert push_lateral_force(theta, mu, nu, f_os_a, f_ts_a, f_z + 5.0) == pytest.approx(f_os_f, rel=1e-10)
    extra = push_lateral_force(theta, mu, nu, f_os_a, f_ts_a, f_z + 5.0, mu_ts=0.3)
    assert extra == pytest.approx(f_os_f + 0.3 * 5.0, rel=1e-10)


def test_min_normal_force_at_zero_angle_is_minus_tip_adhesion():
    assert min_normal_force(0.0, 0.3, 0.2, 20.0, 1.7) == pytest.approx(-1.7)


def test_min_normal_force_grows_with_theta_and_diverges_at_theta_max():
    mu = 0.4
    tmax = float(theta_max_deg(mu))
    th = np.linspace(0.0, tmax - 1e-9, 400)
    fz = min_normal_force(th, mu, 0.2, 20.0, 1.0)
    assert np.all(np.isfinite(fz))
    assert np.all(np.diff(fz) > 0)
    assert fz[-1] > 1e9
    assert min_normal_force(tmax, mu, 0.2, 20.0, 1.0) == math.inf
    assert min_normal_force(tmax + 5.0, mu, 0.2, 20.0, 1.0) == math.inf
    assert tip_object_repulsion(tmax + 5.0, mu, 0.2, 20.0, 1.0) == math.inf


def test_denominator_near_theta_max_is_accurate():
    # cos θ − μ sin θ evaluated as √(1+μ²) sin(θmax − θ): relative error stays small.
    mu, gap = 0.3, 1e-7
    tmax = math.atan(1 / mu)
    th = math.degrees(tmax - gap)
    expected = (mu + 0.2) * math.sin(tmax - gap) / (math.hypot(1, mu) * math.sin(gap)) * 20.0 - 1.0
    assert min_normal_force(th, mu, 0.2, 20.0, 1.0) == pytest.approx(expected, rel=1e-6)


def test_push_outcomes():
    mu, nu, f_os_a, f_ts_a = 0.3, 0.2, 20.0, 1.0
    bar = float(min_normal_force(30.0, mu, nu, f_os_a, f_ts_a))
    assert push_outcome(bar + 0.01, 30.0, mu, nu, f_os_a, f_ts_a) is PushOutcome.MOVES
    assert push_outcome(bar - 0.01, 30.0, mu, nu, f_os_a, f_ts_a) is PushOutcome.SLIPS_OVER
    assert push_outcome(1e9, 80.0, mu, nu, f_os_a, f_ts_a) is PushOutcome.JAMMED
    assert push_succeeds(bar + 0.01, 30.0, mu, nu, f_os_a, f_ts_a)
    assert not push_succeeds(bar - 0.01, 30.0, mu, nu, f_os_a, f_ts_a)


def test_adhesion_alone_keeps_a_shallow_tip_down():
    # F̄z < 0: the tip-substrate adhesion is enough, any F_z ≥ 0 pushes (seed after eq. 4.7).
    assert min_normal_force(2.0, 0.1, 0.1, 5.0, 1.0) < 0
    assert push_succeeds(0.0, 2.0, 0.1, 0.1, 5.0, 1.0)


@pytest.mark.parametrize("kwargs,name", [
    ({"mu_os": -0.1}, "mu_os"), ({"nu": -1.0}, "nu"), ({"f_os_a": math.nan}, "f_os_a"),
    ({"theta_deg": 90.0}, "theta_deg"), ({"f_ts_a": -2.0}, "f_ts_a")])
def test_bad_parameters_are_named(kwargs, name):
    args = {"theta_deg": 20.0, "mu_os": 0.2, "nu": 0.1, "f_os_a": 10.0, "f_ts_a": 1.0} | kwargs
    with pytest.raises(ValueError, match=name):
        min_normal_force(**args)


@given(theta=st.floats(-89.9, 89.9), mu=st.floats(0.0, 10.0), nu=st.floats(0.0, 5.0),
       f_os_a=st.floats(0.0, 1e4), f_ts_a=st.floats(0.0, 1e3), f_z=st.floats(-1e4, 1e4))
def test_no_nan_and_outcome_agrees_with_threshold(theta, mu, nu, f_os_a, f_ts_a, f_z):
    bar = float(min_normal_force(theta, mu, nu, f_os_a, f_ts_a))
    assert not math.isnan(bar)
    assert not math.isnan(float(push_lateral_force(theta, mu, nu, f_os_a, f_ts_a, f_z, mu_ts=0.2)))
    if theta >= 0:
        assert bar >= -f_ts_a - 1e-9
    outcome = push_outcome(f_z, theta, mu, nu, f_os_a, f_ts_a)
    if math.isinf(bar):
        assert outcome is PushOutcome.JAMMED
    else:
        assert (outcome is PushOutcome.MOVES) == (f_z >= bar)


# --- adhesion scaling ------------------------------------------------------------------

def test_pull_off_is_three_quarters_of_adhesion():
    assert adhesion_from_pull_off(7.5) == pytest.approx(10.0)


def test_jkr_radius_is_the_zero_load_root_of_the_jkr_equation():
    r, w, e = 40.0, 0.05, 2.0
    a = float(jkr_contact_radius(r, w, e))
    # a³ = (3R/4E*)[P + 3πwR + √(6πwRP + (3πwR)²)] at P = 0
    assert a**3 == pytest.approx(3 * r / (4 * e) * 6 * math.pi * w * r, rel=1e-12)


def test_jkr_cylinder_halfwidth_has_zero_load():
    r, w, e = 50.0, 0.08, 3.0
    b = float(jkr_contact_halfwidth(r, w, e))
    load = math.pi * e * b**2 / (4 * r) - math.sqrt(2 * math.pi * e * w * b)   # 2-D JKR, per length
    assert load == pytest.approx(0.0, abs=1e-12 * e * b)


@given(rt=st.floats(1.0, 100.0), rp=st.floats(1.0, 500.0), w=st.floats(0.01, 1.0), e=st.floats(0.1, 200.0))
def test_particle_adhesions_scale_with_jkr_areas(rt, rp, w, e):
    f_ot, f_os = particle_adhesions(2.0, rt, rp)
    area = lambda r: math.pi * float(jkr_contact_radius(r, w, e)) ** 2
    a_ts = area(rt)
    assert f_os == pytest.approx(float(adhesion_from_area(2.0, area(rp), a_ts)), rel=1e-9)
    assert f_ot == pytest.approx(float(adhesion_from_area(2.0, area(float(effective_radius(rt, rp))), a_ts)), rel=1e-9)


def test_particle_of_tip_size_has_tip_adhesion_and_doubles_by_two_to_four_thirds():
    assert particle_adhesions(3.0, 10.0, 10.0)[1] == pytest.approx(3.0)
    assert particle_adhesions(3.0, 10.0, 20.0)[1] == pytest.approx(3.0 * 2 ** (4 / 3))


def test_rod_substrate_adhesion_is_proportional_to_length():
    one = float(rod_substrate_adhesion(1.0, 10.0, 50.0, 1000.0, 0.05, 2.0))
    two = float(rod_substrate_adhesion(1.0, 10.0, 50.0, 2000.0, 0.05, 2.0))
    assert two == pytest.approx(2 * one) and one > 0


# --- particle step ---------------------------------------------------------------------

def test_head_on_push_moves_particle_by_the_penetration():
    x, y, hit = particle_step(0.0, 0.0, 100.0, -65.0, 0.0, 15.0, 0.0, tip_radius=10.0)
    assert hit and (x, y) == (pytest.approx(10.0), pytest.approx(0.0))   # 15 − 5 gap


def test_no_contact_and_zero_step_leave_particle_alone():
    assert particle_step(0.0, 0.0, 100.0, -80.0, 0.0, 10.0, 0.0) == (0.0, 0.0, False)
    assert particle_step(0.0, 0.0, 100.0, -50.0, 0.0, 0.0, 0.0) == (0.0, 0.0, False)


def test_particle_step_rejects_bad_diameter():
    with pytest.raises(ValueError, match="diameter"):
        particle_step(0.0, 0.0, -1.0, 0.0, 0.0, 1.0, 0.0)


@given(px=st.floats(-100, 100), py=st.floats(-100, 100), d=st.floats(1.0, 200.0),
       ang=st.floats(-math.pi, math.pi), gap=st.floats(0.0, 1.0), step=st.floats(0.0, 20.0),
       dang=st.floats(-math.pi, math.pi), tr=st.floats(0.0, 20.0))
def test_particle_step_invariants(px, py, d, ang, gap, step, dang, tr):
    rc = d / 2 + tr
    tx, ty = px + (rc + gap) * math.cos(ang), py + (rc + gap) * math.sin(ang)
    dx, dy = step * math.cos(dang), step * math.sin(dang)
    x, y, hit = particle_step(px, py, d, tx, ty, dx, dy, tr)
    assert math.isfinite(x) and math.isfinite(y)
    ex, ey = tx + dx, ty + dy
    if hit:
        assert math.hypot(x - ex, y - ey) == pytest.approx(rc, rel=1e-9, abs=1e-9)
        # moves along the contact normal: away from the tip's end point
        assert (x - px) * (px - ex) + (y - py) * (py - ey) >= -1e-9 * (1 + rc * step)
    else:
        assert (x, y) == (px, py)
