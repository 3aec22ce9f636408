"""Cantilever frames, forces from signals, compensation, calibration, tip position (seed ch. 3)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from nanoasm.world.cantilever import (
    Cantilever,
    baseline_index,
    calibrate_lateral_gain,
    compensate_signals,
    compensated_command,
    crosstalk_from_force_curve,
    force_from_signals,
    motion_angle_deg,
    normal_gain_from_force_curve,
    photodiode_signals,
    raw_signals,
    scan_rotation,
    signals_from_force,
    tip_deflection,
    tip_force_afm,
    tip_offset,
    to_afm,
    to_cantilever,
    twist_angle_deg,
)

LEVER = Cantilever()


# --- frames ----------------------------------------------------------------------------

@given(psi=st.floats(-720, 720))
def test_scan_rotation_is_a_rotation(psi):
    r = scan_rotation(psi)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)


def test_scan_rotation_special_angles():
    # §3.6.4: at ψ = 0 the AFM frame is the cantilever frame turned by 180°
    np.testing.assert_allclose(scan_rotation(0.0), np.diag([-1.0, -1.0, 1.0]), atol=1e-15)
    np.testing.assert_allclose(scan_rotation(180.0), np.eye(3), atol=1e-15)


@given(psi=st.floats(-360, 360), v=st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3))
def test_frame_round_trip(psi, v):
    np.testing.assert_allclose(to_afm(to_cantilever(v, psi), psi), v, atol=1e-9)
    np.testing.assert_allclose(to_cantilever(v[:2], psi), to_cantilever(v, psi)[:2], atol=1e-12)


def test_motion_angle():
    assert motion_angle_deg([1.0, 0.0], 180.0) == pytest.approx(0.0)
    assert abs(motion_angle_deg([1.0, 0.0], 0.0)) == pytest.approx(180.0)
    assert motion_angle_deg([0.0, 0.0], 30.0) == 0.0


# --- signals and forces ----------------------------------------------------------------

def test_photodiode_signals():
    s_n, s_l = photodiode_signals(3.0, 1.0, 1.0, 1.0)
    assert s_n == pytest.approx(10 * (4 - 2) / 6) and s_l == pytest.approx(10 * (4 - 2) / 6)
    s_n, s_l = photodiode_signals(1.0, 1.0, 1.0, 1.0)
    assert s_n == 0.0 and s_l == 0.0
    with pytest.raises(ValueError, match="photodiode"):
        photodiode_signals(0.0, 0.0, 0.0, 0.0)


def test_pure_normal_force():
    f = force_from_signals(1.5, 0.0, 90.0)
    np.testing.assert_allclose(f, [0.0, 0.0, 0.12 * 89.0 * 1.5], atol=1e-12)


@given(fl=st.floats(0.0, 100.0), fz=st.floats(-50.0, 50.0), phi=st.floats(-180.0, 180.0))
def test_force_round_trip_outside_the_floor(fl, fz, phi):
    floor = 5.0
    p = math.radians(phi)
    if abs(math.sin(p)) < math.sin(math.radians(floor)):
        return
    force = np.array([-fl * math.cos(p), -fl * math.sin(p), fz])   # lateral force opposes motion
    s_n, s_l = signals_from_force(force)
    np.testing.assert_allclose(force_from_signals(s_n, s_l, phi, phi_floor_deg=floor), force,
                               rtol=1e-9, atol=1e-9)


@given(s_l=st.floats(-10, 10), s_n=st.floats(-10, 10), phi=st.floats(-1e-3, 1e-3) | st.floats(-180, 180),
       floor=st.floats(0.5, 30.0))
def test_force_is_bounded_near_the_singular_direction(s_l, s_n, phi, floor):
    f = force_from_signals(s_n, s_l, phi, phi_floor_deg=floor)
    assert np.all(np.isfinite(f))
    assert abs(f[0]) <= abs(f[1]) / math.sin(math.radians(floor)) * (1 + 1e-12)


def test_force_at_phi_zero_and_continuity_at_floor():
    assert force_from_signals(1.0, 0.2, 0.0)[0] == 0.0
    assert force_from_signals(1.0, 0.2, 180.0)[0] == pytest.approx(0.0, abs=1e-12)
    below = force_from_signals(1.0, 0.2, 5.0 - 1e-9)[0]
    above = force_from_signals(1.0, 0.2, 5.0 + 1e-9)[0]
    assert below == pytest.approx(above, rel=1e-6)


def test_signals_saturate_at_full_scale():
    s_n, s_l = signals_from_force([0.0, 1e6, 1e6])
    assert (s_n, s_l) == (10.0, 10.0)


def test_tip_force_afm_composes_eq_3_11_and_3_12():
    v, psi = np.array([0.3, 1.0]), 30.0
    phi = float(motion_angle_deg(v, psi))
    expect = to_afm(force_from_signals(0.4, -0.05, phi), psi)
    np.testing.assert_allclose(tip_force_afm(0.4, -0.05, v, psi), expect)


def test_twist_angle_uses_kn_over_l():
    assert twist_angle_deg(1.0) == pytest.approx(math.degrees(89.0 / 200_000.0))


# --- compensation ----------------------------------------------------------------------

@pytest.mark.parametrize("n", [3, 5, 21, 101])
def test_baseline_index_matches_seed_formula_for_odd_n(n):
    size = 5000.0
    xs = np.linspace(-size / 2, size / 2, 997)
    i, j = baseline_index(xs, -xs, size, n)
    # eq. 3.29 with int(n/2) = (n−1)/2 for odd n and int(*) rounding half up
    seed_i = np.floor((n - 1) * xs / size + 0.5) + (n - 1) // 2
    seed_j = (n - 1) // 2 - np.floor((n - 1) * -xs / size + 0.5)
    np.testing.assert_array_equal(i, seed_i)
    np.testing.assert_array_equal(j, np.clip(seed_j, 0, n - 1))


@given(x=st.floats(-1e5, 1e5), y=st.floats(-1e5, 1e5), n=st.integers(1, 64))
def test_baseline_index_stays_in_the_matrix(x, y, n):
    i, j = baseline_index(x, y, 5000.0, n)
    assert 0 <= i < n and 0 <= j < n


def test_baseline_index_corners():
    assert baseline_index(-2500.0, 2500.0, 5000.0, 4) == (0, 0)      # top left
    assert baseline_index(2500.0, -2500.0, 5000.0, 4) == (3, 3)      # bottom right


def test_compensation_of_a_known_baseline():
    a = np.arange(9.0).reshape(3, 3)            # a[j, i]
    b = 10 * np.arange(9.0).reshape(3, 3)
    # tip at the top-right corner: i = 2, j = 0
    sn_bar, sl_bar = compensate_signals(5.0, 30.0, 100.0, 100.0, a, b, 200.0, 0.18)
    assert sn_bar == pytest.approx(5.0 - 2.0)
    assert sl_bar == pytest.approx(30.0 - 20.0 - 0.18 * 3.0)


@given(sn=st.floats(-10, 10), sl=st.floats(-10, 10), x=st.floats(-600, 600), y=st.floats(-600, 600),
       alpha=st.floats(-1, 1))
def test_compensation_round_trip(sn, sl, x, y, alpha):
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(16, 16)), rng.normal(size=(16, 16))
    raw = raw_signals(sn, sl, x, y, a, b, 1000.0, alpha)
    np.testing.assert_allclose(compensate_signals(*raw, x, y, a, b, 1000.0, alpha), (sn, sl), atol=1e-12)


def test_scalar_baseline_and_bad_shape():
    assert compensate_signals(-1.2, 0.12, 0.0, 0.0, 0.8, 0.12, 1000.0, 0.0) == (pytest.approx(-2.0), pytest.approx(0.0))
    with pytest.raises(ValueError, match="baseline_n"):
        compensate_signals(0.0, 0.0, 0.0, 0.0, np.zeros((3, 4)), 0.0, 1000.0, 0.0)


# --- calibration -----------------------------------------------------------------------

def test_normal_gain_and_crosstalk_from_a_force_curve():
    rng = np.random.default_rng(11)
    s_n = np.linspace(-2.0, 6.0, 200)
    z = 89.0 * s_n + 40.0 + rng.normal(0, 0.5, s_n.size)
    s_l = 0.18 * s_n - 0.3 + rng.normal(0, 0.002, s_n.size)
    assert normal_gain_from_force_curve(z, s_n) == pytest.approx(89.0, rel=2e-3)
    assert normal_gain_from_force_curve(-z, s_n) == pytest.approx(89.0, rel=2e-3)
    assert crosstalk_from_force_curve(s_n, s_l) == pytest.approx(0.18, abs=2e-3)
    with pytest.raises(ValueError, match="does not vary"):
        normal_gain_from_force_curve([1.0, 2.0], [0.5, 0.5])


def test_seed_calibration_example():
    cal = calibrate_lateral_gain(0.02, 0.07, 9.09)            # errata pairing, k = 0.12, K_n = 89
    assert cal.lateral_gain == pytest.approx(38.27, abs=0.005)
    assert cal.mu == pytest.approx(0.0873, abs=5e-5)
    # the seed's graphical reading: 37.8 nN/V within 1.5 %; 0.086 is 1.52 % from μ = 0.08733
    assert 37.8 == pytest.approx(cal.lateral_gain, rel=0.015)
    assert 0.086 == pytest.approx(cal.mu, rel=0.016)
    assert 0.086 == pytest.approx(round(cal.mu, 4), rel=0.015)


def test_calibration_solves_eq_3_26_and_3_27():
    th, sm, sp = math.radians(9.09), 0.02, 0.07
    cal = calibrate_lateral_gain(sm, sp, 9.09)
    g, mu = cal.lateral_gain / (0.12 * 89.0), cal.mu
    assert g * sm - (math.sin(th) - mu * math.cos(th)) / (math.cos(th) + mu * math.sin(th)) == pytest.approx(0, abs=1e-13)
    assert g * sp - (math.sin(th) + mu * math.cos(th)) / (math.cos(th) - mu * math.sin(th)) == pytest.approx(0, abs=1e-13)
    # derived closed form: sin 2λ = sin 2θ (s₊ − s₋)/(s₊ + s₋), λ = atan μ
    lam = 0.5 * math.asin(math.sin(2 * th) * (sp - sm) / (sp + sm))
    assert mu == pytest.approx(math.tan(lam), rel=1e-12)


def test_seed_pairing_is_rejected():
    with pytest.raises(ValueError, match="mu < 0"):
        calibrate_lateral_gain(0.07, 0.02, 9.09)


def test_default_lateral_gain_matches_the_calibration():
    assert LEVER.lateral_gain == pytest.approx(calibrate_lateral_gain(0.02, 0.07, 9.09).lateral_gain, abs=0.005)


def _tilted_surface(f_n: float, theta: float, mu: float, adhesion: float, sign: int) -> float:
    """Lateral force on a tilted surface from the force balance behind eq. 3.18–3.21.

    sign = −1: friction opposes the slope's lateral term (eq. 3.18, 3.20);
    sign = +1: friction adds to it (eq. 3.19, 3.21).
    """
    c, s = math.cos(theta), math.sin(theta)
    # F_n = N cos θ − sign (μN + A) sin θ ; F_l = N sin θ + sign (μN + A) cos θ
    n = (f_n + sign * adhesion * s) / (c - sign * mu * s)
    return n * s + sign * (mu * n + adhesion) * c


@pytest.mark.parametrize("sign", [-1, 1])
def test_finite_difference_of_lateral_against_normal_force(sign):
    th, mu, adhesion, h = math.radians(9.09), 0.0873, 3.0, 1e-4
    fd = (_tilted_surface(20 + h, th, mu, adhesion, sign) - _tilted_surface(20 - h, th, mu, adhesion, sign)) / (2 * h)
    analytic = (math.sin(th) + sign * mu * math.cos(th)) / (math.cos(th) - sign * mu * math.sin(th))
    assert fd == pytest.approx(analytic, rel=1e-8)


def test_calibration_recovers_a_simulated_friction_loop():
    lever = Cantilever(lateral_gain=41.0)
    th, mu, adhesion = math.radians(12.0), 0.15, 2.0
    f_n = np.linspace(5.0, 60.0, 12)
    slopes = []
    for sign in (-1, 1):
        f_l = np.array([_tilted_surface(f, th, mu, adhesion, sign) for f in f_n])
        s_n, _ = signals_from_force(np.stack([0 * f_n, 0 * f_n, f_n], axis=-1), lever)
        s_l = f_l / lever.lateral_gain
        slopes.append(np.polyfit(s_n, s_l, 1)[0])
    cal = calibrate_lateral_gain(slopes[0], slopes[1], 12.0, lever.spring_constant, lever.normal_gain)
    assert cal.lateral_gain == pytest.approx(41.0, rel=1e-9)
    assert cal.mu == pytest.approx(0.15, rel=1e-9)


# --- tip position ----------------------------------------------------------------------

def test_c1_from_kn_h_over_l():
    assert LEVER.c1 == pytest.approx(89.0 * 3000.0 / 200_000.0)
    assert abs(LEVER.c1 - 1.34) <= 0.005 + 1e-12
    assert LEVER.c1 == pytest.approx(1.3, rel=0.03)
    assert Cantilever(c1_override=1.3).c1 == 1.3


def test_c2_reproduces_seed_line_spacing():
    # §3.6.4: depths 0.5 µm apart (virtual Ŝn = d/K_n) give lines ≈ 130 nm apart
    dx = tip_deflection(500.0 / 89.0, 0.0)[0]
    assert dx == pytest.approx(130.0, rel=0.01)


def test_deeper_push_shifts_tip_along_negative_afm_x_at_psi_zero():
    off = tip_offset(2.0, 0.0, 0.0)
    assert off[0] == pytest.approx(-23.0 * 2.0) and off[1] == pytest.approx(0.0)
    assert off[2] == pytest.approx(89.0 * 2.0)


@given(tx=st.floats(-1e4, 1e4), ty=st.floats(-1e4, 1e4), sn=st.floats(-10, 10), sl=st.floats(-10, 10),
       psi=st.floats(0, 360))
def test_compensated_command_puts_tip_on_target(tx, ty, sn, sl, psi):
    cmd = compensated_command([tx, ty], sn, sl, psi)
    tip = cmd + tip_offset(sn, sl, psi)[:2]
    np.testing.assert_allclose(tip, [tx, ty], atol=1e-9)


@pytest.mark.parametrize("field,value", [("spring_constant", -0.1), ("normal_gain", math.nan),
                                         ("tip_height", 0.0), ("c1_override", -1.0), ("crosstalk", math.inf)])
def test_cantilever_validation_names_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        Cantilever(**{field: value})


def test_negative_crosstalk_is_allowed():
    assert Cantilever(crosstalk=-0.05).crosstalk == -0.05
