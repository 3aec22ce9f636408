"""Rod pivot, push force, tip–rod equilibrium (seed eq. 4.8–4.20) and the rod step."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st
from scipy.optimize import minimize_scalar

from nanoasm.world.particle_push import PushOutcome
from nanoasm.world.pivot import (
    Regime,
    RodPose,
    aspect_regime,
    min_push_force,
    pivot_position,
    push_force_for_pivot,
    rho,
    rod_friction,
    rod_min_normal_force,
    rod_push_outcome,
    rod_step,
    rod_theta_max_deg,
    rod_tip_repulsion,
)

SQ2 = math.sqrt(2.0)
L = 1000.0


# --- pivot and force -------------------------------------------------------------------

def test_pivot_never_in_forbidden_interval():
    ls = np.linspace(0.0, L, 200_001)
    for branch in (-1, 1):
        s = pivot_position(ls, L, branch)
        inside = (s > (1 - SQ2 / 2) * L + 1e-9) & (s < SQ2 / 2 * L - 1e-9)
        assert not inside.any()
        assert np.all((s >= 0) & (s <= L))


@given(l_frac=st.floats(0.0, 1.0), length=st.floats(1e-3, 1e6), branch=st.sampled_from([-1, 1]))
def test_pivot_never_in_forbidden_interval_property(l_frac, length, branch):
    s = float(pivot_position(l_frac * length, length, branch)) / length
    assert not (1 - SQ2 / 2 + 1e-12 < s < SQ2 / 2 - 1e-12)
    assert math.isfinite(s)


@pytest.mark.parametrize("l", [0.0, 100.0, 333.0, 499.9, 500.1, 777.0, 1000.0])
def test_pivot_solves_the_stationarity_condition(l):
    # dF/ds = 0 of eq. 4.8 is s² − 2ls + lL − L²/2 = 0 (eq. 4.9 prints +L²/2; 4.10 solves −).
    s = float(pivot_position(l, L))
    assert s * s - 2 * l * s + l * L - L * L / 2 == pytest.approx(0.0, abs=1e-9 * L * L)


@pytest.mark.parametrize("l", [0.0, 120.0, 400.0, 620.0, 1000.0])
def test_pivot_minimises_push_force_of_eq_4_8(l):
    s_star = float(pivot_position(l, L))
    lo, hi = (l + 1e-6, L) if l < L / 2 else (0.0, l - 1e-6)
    best = minimize_scalar(lambda s: float(push_force_for_pivot(s, l, L, 1.0)), bounds=(lo, hi),
                           method="bounded", options={"xatol": 1e-9})
    assert best.x == pytest.approx(s_star, abs=1e-4)
    assert best.fun == pytest.approx(float(min_push_force(l, L, 1.0)), rel=1e-9)


@pytest.mark.parametrize("l", [50.0, 300.0, 700.0, 950.0])
def test_finite_difference_derivative_vanishes_at_pivot(l):
    s, h = float(pivot_position(l, L)), 1e-3
    f = lambda x: float(push_force_for_pivot(x, l, L, 1.0))
    d1 = (f(s + h) - f(s - h)) / (2 * h)
    d2 = (f(s + h) - 2 * f(s) + f(s - h)) / h**2
    assert abs(d1) < 1e-6 * f(s) / L
    assert d2 > 0


def test_minimum_push_force_at_end_and_middle():
    f = 0.02
    assert min_push_force(0.0, L, f) == pytest.approx((SQ2 - 1) * f * L, rel=1e-14)
    assert min_push_force(L, L, f) == pytest.approx((SQ2 - 1) * f * L, rel=1e-14)
    assert min_push_force(L / 2, L, f) == pytest.approx(f * L, rel=1e-14)


def test_push_force_at_end_equals_eq_4_8_with_pivot_at_l_over_root_two():
    assert push_force_for_pivot(L / SQ2, 0.0, L, 1.0) == pytest.approx((SQ2 - 1) * L, rel=1e-14)


def test_rho_symmetric_and_between_bounds():
    ls = np.linspace(0, L, 1001)
    r = rho(ls, L)
    np.testing.assert_allclose(r, rho(L - ls, L), rtol=1e-14)
    assert r.min() == pytest.approx(SQ2 - 1) and r.max() == pytest.approx(1.0)
    # eq. 4.13: ρ = 2s/L − 1 for l < L/2 and (errata) 1 − 2s/L for l > L/2
    left, right = ls[ls < L / 2], ls[ls > L / 2]
    np.testing.assert_allclose(rho(left, L), 2 * (left + np.sqrt(left**2 - left * L + L**2 / 2)) / L - 1, rtol=1e-12)
    np.testing.assert_allclose(rho(right, L), 1 - 2 * (right - np.sqrt(right**2 - right * L + L**2 / 2)) / L, rtol=1e-12)
    # the printed "+" form for l > L/2 would leave [√2 − 1, 1]:
    printed = 1 - 2 * (right + np.sqrt(right**2 - right * L + L**2 / 2)) / L
    assert np.all(printed < 0)


def test_bifurcation_branches_and_limits():
    assert pivot_position(L / 2, L, branch=1) == L
    assert pivot_position(L / 2, L, branch=-1) == 0.0
    assert pivot_position(L / 2 - 1e-9, L) == pytest.approx(L, abs=1e-8)
    assert pivot_position(L / 2 + 1e-9, L) == pytest.approx(0.0, abs=1e-8)
    with pytest.raises(ValueError, match="branch"):
        pivot_position(L / 2, L, branch=0)


def test_push_point_outside_rod_is_rejected():
    with pytest.raises(ValueError, match="l must"):
        pivot_position(1001.0, L)


def test_aspect_regimes():
    assert aspect_regime(1300, 100) is Regime.RIGID
    assert aspect_regime(1500, 100) is Regime.UNCERTAIN
    assert aspect_regime(2500, 100) is Regime.UNCERTAIN
    assert aspect_regime(3000, 100) is Regime.FLEXIBLE


# --- tip–rod equilibrium ---------------------------------------------------------------

@pytest.mark.parametrize("l", [0.0, 250.0, 500.0, 900.0])
def test_rod_min_normal_force_matches_equilibrium_solve(l):
    theta, mu, nu, f_os_a, f_ot_a, f_ts_a = 30.0, 0.3, 0.2, 50.0, 2.0, 1.0
    r = float(rho(l, L))
    c, s = math.cos(math.radians(theta)), math.sin(math.radians(theta))
    # 4.15, 4.16, 4.17 with F^f_ot = F^r_ts = 0 and F^f_os = ρ(μ F^r_os + ν F^a_os) (4.14)
    a = np.array([[c, 0, -1, 0], [s, -1, 0, 0], [-s, 0, 0, 1], [0, -r * mu, 1, 0]], dtype=float)
    b = np.array([f_ot_a * c, f_ot_a * s - f_os_a, -f_ot_a * s - f_ts_a, r * nu * f_os_a])
    f_ot_r, _, _, f_z = np.linalg.solve(a, b)
    assert rod_min_normal_force(l, L, theta, mu, nu, f_os_a, f_ts_a) == pytest.approx(f_z, rel=1e-10)
    assert rod_tip_repulsion(l, L, theta, mu, nu, f_os_a, f_ot_a) == pytest.approx(f_ot_r, rel=1e-10)


def test_rod_theta_max_and_end_push_is_easier():
    mu = 0.5
    assert rod_theta_max_deg(L / 2, L, mu) == pytest.approx(math.degrees(math.atan(1 / mu)))
    assert rod_theta_max_deg(0.0, L, mu) == pytest.approx(math.degrees(math.atan(1 / ((SQ2 - 1) * mu))))
    end = rod_min_normal_force(0.0, L, 30.0, mu, 0.2, 50.0, 1.0)
    mid = rod_min_normal_force(L / 2, L, 30.0, mu, 0.2, 50.0, 1.0)
    assert end < mid


def test_rod_push_outcome_and_friction():
    bar = float(rod_min_normal_force(0.0, L, 30.0, 0.3, 0.2, 50.0, 1.0))
    assert rod_push_outcome(bar + 1e-6, 0.0, L, 30.0, 0.3, 0.2, 50.0, 1.0) is PushOutcome.MOVES
    assert rod_push_outcome(bar - 1e-6, 0.0, L, 30.0, 0.3, 0.2, 50.0, 1.0) is PushOutcome.SLIPS_OVER
    assert rod_friction(0.3, 0.2, 10.0, 50.0) == pytest.approx(13.0)


# --- rod step --------------------------------------------------------------------------

def fixed_point(old: RodPose, new: RodPose) -> complex:
    """Centre of the rotation that maps ``old`` onto ``new``."""
    rot = complex(math.cos(math.radians(new.angle - old.angle)), math.sin(math.radians(new.angle - old.angle)))
    c0, c1 = complex(old.x, old.y), complex(new.x, new.y)
    return (c1 - rot * c0) / (1 - rot)


def ends(p: RodPose) -> tuple[complex, complex]:
    e = complex(math.cos(math.radians(p.angle)), math.sin(math.radians(p.angle))) * p.length / 2
    return complex(p.x, p.y) - e, complex(p.x, p.y) + e


@pytest.mark.parametrize("side", [-1.0, 1.0])
def test_push_at_end_rotates_about_l_over_root_two_from_pushed_end(side):
    pose = RodPose(100.0, -50.0, 30.0, L, 100.0)
    a_end, _ = ends(pose)
    e = complex(math.cos(math.radians(30)), math.sin(math.radians(30)))
    n = e * 1j
    tip = a_end + side * 60.0 * n                # 10 nm clear of the side, at the very end
    step = -side * 12.0 * n                      # 2 nm into the rod, perpendicular
    out = rod_step(pose, (tip.real, tip.imag), (step.real, step.imag))
    assert out.contact
    fp = fixed_point(pose, out.pose)
    assert abs(fp - (a_end + e * L / SQ2)) < 1e-6
    assert abs(complex(*out.pivot) - fp) < 1e-6
    # pushed end moves along the push, by the 2 nm penetration to first order
    a_new, _ = ends(out.pose)
    assert ((a_new - a_end) / (-side * n)).real == pytest.approx(2.0, rel=1e-3)


def test_tip_stays_on_the_side_after_contact():
    pose = RodPose(0.0, 0.0, 0.0, L, 80.0)
    out = rod_step(pose, (-300.0, -45.0), (3.0, 10.0), tip_radius=5.0)
    p = out.pose
    t = math.radians(p.angle)
    v = -(-297.0 - p.x) * math.sin(t) + (-35.0 - p.y) * math.cos(t)
    assert out.contact and v == pytest.approx(-45.0, abs=1e-9)


@pytest.mark.parametrize("branch", [-1, 1])
def test_push_exactly_at_middle_follows_branch(branch):
    pose = RodPose(0.0, 0.0, 0.0, L, 100.0)
    out = rod_step(pose, (0.0, -50.0), (0.0, 1.0), branch=branch)
    assert out.contact and out.pivot == (pytest.approx(branch * L / 2), pytest.approx(0.0))
    assert out.pose.angle * branch < 0          # pushed up at the middle, about the end
    assert math.isfinite(out.pose.x) and math.isfinite(out.pose.y)


def test_quarter_point_push_uses_pivot_of_eq_4_10():
    pose = RodPose(0.0, 0.0, 0.0, L, 100.0)
    out = rod_step(pose, (-250.0, -50.0), (0.0, 0.5))
    s = float(pivot_position(250.0, L))
    assert abs(fixed_point(pose, out.pose) - complex(s - L / 2, 0.0)) < 1e-5


def test_no_contact_cases():
    pose = RodPose(0.0, 0.0, 0.0, L, 100.0)
    same = lambda out: not out.contact and out.pose == pose and out.pivot is None
    assert same(rod_step(pose, (-300.0, -50.0), (0.0, 0.0)))           # zero step, touching
    assert same(rod_step(pose, (-300.0, -80.0), (0.0, 10.0)))          # stops short
    assert same(rod_step(pose, (-300.0, -50.0), (0.0, -5.0)))          # moves away
    assert same(rod_step(pose, (-510.0, -80.0), (0.0, 60.0)))          # past the end
    assert same(rod_step(pose, (-520.0, 0.0), (30.0, 0.0)))            # end-on: slips over


def test_tip_leaves_the_rod_past_its_end():
    pose = RodPose(0.0, 0.0, 0.0, L, 100.0)
    tip = np.array([-470.0, -50.0])
    contacts = []
    for _ in range(2000):                         # straight push, 0.5 nm steps
        out = rod_step(pose, tuple(tip), (0.0, 0.5))
        pose, tip = out.pose, tip + (0.0, 0.5)
        contacts.append(out.contact)
    assert contacts[0] and not contacts[-1]
    assert -90 < pose.angle < -1                  # pushed up near the left end: turns clockwise
    first_off = contacts.index(False)
    assert not any(contacts[first_off + 1:])      # once past the end, the rod is left behind
    t = math.radians(pose.angle)
    u_end = (tip[0] - pose.x) * math.cos(t) + (tip[1] - pose.y) * math.sin(t)
    assert u_end < -L / 2                          # the tip left past the pushed end


def test_result_is_independent_of_step_size():
    def run(n):
        pose, tip = RodPose(0.0, 0.0, 10.0, L, 100.0), np.array([-350.0, -120.0])
        for _ in range(n):
            d = np.array([0.0, 150.0]) / n
            pose = rod_step(pose, tuple(tip), tuple(d)).pose
            tip = tip + d
        return pose
    coarse, fine = run(300), run(3000)
    assert coarse.angle == pytest.approx(fine.angle, abs=0.02)
    assert math.hypot(coarse.x - fine.x, coarse.y - fine.y) < 0.2


@pytest.mark.parametrize("u", [-500.0, -500.0 + 1e-12, -1e-13, 0.0, 1e-13, 500.0 - 1e-12, 500.0])
@pytest.mark.parametrize("dv", [0.0, 1e-15, 1e-9, 5.0])
def test_step_is_finite_at_the_hard_points(u, dv):
    pose = RodPose(0.0, 0.0, 0.0, L, 100.0)
    out = rod_step(pose, (u, -50.0 + 1e-12), (0.0, dv))
    assert all(math.isfinite(v) for v in out.pose)


def test_invalid_step_input():
    with pytest.raises(ValueError, match="length"):
        rod_step(RodPose(0, 0, 0, 0.0, 10.0), (0, 0), (0, 1))
    with pytest.raises(ValueError, match="finite"):
        rod_step(RodPose(0, 0, 0, L, 10.0), (math.nan, 0), (0, 1))
    with pytest.raises(ValueError, match="branch"):
        rod_step(RodPose(0, 0, 0, L, 10.0), (0, -5), (0, 1), branch=2)


coord = st.floats(-2000, 2000)


@given(x=coord, y=coord, ang=st.floats(-720, 720), length=st.floats(50, 5000), aspect=st.floats(2.5, 25),
       u=st.floats(-0.6, 0.6), v=st.floats(-1.5, 1.5), sx=st.floats(-20, 20), sy=st.floats(-20, 20),
       tr=st.floats(0, 10), branch=st.sampled_from([-1, 1]))
def test_step_invariants(x, y, ang, length, aspect, u, v, sx, sy, tr, branch):
    d = length / aspect
    assume(tr < 0.2 * d)
    pose = RodPose(x, y, ang, length, d)
    t = math.radians(ang)
    e, n = complex(math.cos(t), math.sin(t)), complex(-math.sin(t), math.cos(t))
    tip = complex(x, y) + u * length * e + v * (d / 2 + tr) * n
    out = rod_step(pose, (tip.real, tip.imag), (sx, sy), tip_radius=tr, branch=branch)
    new = out.pose
    assert all(math.isfinite(q) for q in new)
    assert (new.length, new.diameter) == (length, d)
    a, b = ends(new)
    assert abs(b - a) == pytest.approx(length, rel=1e-12)
    assert -180.0 <= new.angle < 180.0 or not out.contact
    if out.contact:
        # the pivot is a fixed point of the motion and lies on the axis, outside the gap
        px, py = out.pivot
        p_old = ((complex(px, py) - complex(x, y)) / e).real
        t1 = math.radians(new.angle)
        e1 = complex(math.cos(t1), math.sin(t1))
        assert abs(complex(new.x, new.y) + p_old * e1 - complex(px, py)) < 1e-7 * (1 + length)
        assert abs(p_old) >= (SQ2 - 1) * length / 2 * (1 - 1e-9)
        # the tip ends on the rod's side (no overlap left), aspect ≥ 2.5 keeps it reachable
        end = tip + complex(sx, sy)
        lateral = ((end - complex(new.x, new.y)) / e1).imag
        assert abs(lateral) == pytest.approx(d / 2 + tr, rel=1e-9, abs=1e-7)


def test_step_is_cheap():
    pose = RodPose(0.0, 0.0, 0.0, L, 100.0)
    start = time.perf_counter()
    for _ in range(10_000):
        rod_step(pose, (-300.0, -55.0), (0.1, 6.0))
    assert time.perf_counter() - start < 1.0      # ≈ 3 µs a call here; 10⁴ calls in < 1 s
