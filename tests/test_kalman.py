"""Drift filter: closed forms, textbook agreement, Joseph-form robustness, convergence and
consistency, gating, creep, RTS smoothing, determinism."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st
from nanoasm.drift import (
    H_OFFSET,
    CreepHistory,
    CreepModelParams,
    DriftFilter,
    DriftFilterParams,
    creep_offset,
    creep_rate,
    fuse,
    gate,
    gate_threshold,
    joint_nis,
    predict,
    predict_sqrt,
    process_noise,
    process_noise_sqrt,
    psd_sqrt,
    rts,
    select_consistent,
    smooth,
    transition,
    tria,
    update,
    update_sqrt,
    weighted_mean,
)
from nanoasm.drift.creep import creep_tau_sensitivity
from scipy.integrate import quad_vec

# -- helpers ---------------------------------------------------------------------------------


def naive_predict(x, P, dt, q):
    F = np.array([[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]], float)
    b = np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    Q = q * np.kron(b, np.eye(2))  # state order dx, dy, vx, vy
    return F @ x, F @ P @ F.T + Q


def naive_update(x, P, z, R, H=H_OFFSET):
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    v = z - H @ x
    return x + K @ v, (np.eye(4) - K @ H) @ P, v, S, v @ np.linalg.inv(S) @ v


def random_spd(rng, n, log_lo, log_hi):
    Qm, _ = np.linalg.qr(rng.standard_normal((n, n)))
    return Qm @ np.diag(10.0 ** rng.uniform(log_lo, log_hi, n)) @ Qm.T


def assert_psd(P, rel=1e-9):
    assert np.all(np.isfinite(P))
    assert np.array_equal(P, P.T)
    eig = np.linalg.eigvalsh(P)
    assert eig[0] >= -rel * max(1.0, eig[-1]), eig


def simulate_drift(rng, t_end, v0, w, h=0.5):
    """Truth on a fine grid, independent of the filter's discretisation: velocity random
    walk of intensity w (nm/s per √s), position by the trapezoidal rule."""
    n = round(t_end / h)
    dv = rng.standard_normal((n, 2)) * w * math.sqrt(h)
    v = np.vstack([v0, v0 + np.cumsum(dv, axis=0)])
    x = np.vstack([np.zeros(2), np.cumsum(h * 0.5 * (v[1:] + v[:-1]), axis=0)])
    return np.arange(n + 1) * h, x, v


def run_tracking(seed, *, t_end=7200.0, v0=(0.3, -0.1), w=5e-4, epoch=0.0):
    """Measure a simulated drift every 20-40 s with 1-2 nm noise; return truth and filter."""
    rng = np.random.default_rng(seed)
    tg, xg, vg = simulate_drift(rng, t_end, np.asarray(v0), w)
    f = DriftFilter(DriftFilterParams(q=w**2, offset_std=10.0, velocity_std=0.5), epoch=epoch)
    t = 0.0
    rows = []
    while True:
        t += rng.uniform(20.0, 40.0)
        k = round(t / 0.5)
        if k >= tg.size:
            break
        t = tg[k]
        sigma = rng.uniform(1.0, 2.0)
        f.measure(epoch + t, xg[k] + rng.normal(0.0, sigma, 2), sigma**2 * np.eye(2))
        rows.append((t, xg[k], vg[k], f.x, f.P))
    return f, rows


# -- discretisation --------------------------------------------------------------------------


def test_transition_closed_form_and_semigroup():
    F = transition(2.5)
    assert np.array_equal(F, np.array([[1, 0, 2.5, 0], [0, 1, 0, 2.5], [0, 0, 1, 0], [0, 0, 0, 1.0]]))
    assert np.allclose(transition(1.2) @ transition(3.4), transition(4.6), rtol=0, atol=1e-14)
    assert np.array_equal(transition(0.0), np.eye(4))


@pytest.mark.parametrize("dt", [0.0, 1e-3, 0.7, 30.0, 1e5])
def test_process_noise_closed_form(dt):
    q, qo = 2.5e-7, 0.04
    Q = process_noise(dt, q, qo)
    axis = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]]) + np.diag([qo * dt, 0.0])
    for a in (0, 1):
        idx = np.ix_([a, a + 2], [a, a + 2])
        assert np.allclose(Q[idx], axis, rtol=1e-12, atol=0)
    assert Q[0, 1] == Q[0, 3] == Q[1, 2] == 0.0
    assert_psd(Q)
    L = process_noise_sqrt(dt, q, qo)
    assert np.allclose(L @ L.T, Q, rtol=1e-12, atol=0)


def test_process_noise_is_the_integral():
    dt, q = 7.3, 0.2
    G = np.array([[0, 0], [0, 0], [1, 0], [0, 1.0]])
    integral, _ = quad_vec(lambda s: transition(s) @ G @ (q * np.eye(2)) @ G.T @ transition(s).T,
                           0.0, dt, epsabs=1e-13, epsrel=1e-12)
    assert np.allclose(process_noise(dt, q), integral, rtol=1e-10, atol=1e-12)


def test_process_noise_composes_over_steps():
    a, b, q = 13.0, 29.5, 1e-3
    Fb = transition(b)
    assert np.allclose(Fb @ process_noise(a, q) @ Fb.T + process_noise(b, q),
                       process_noise(a + b, q), rtol=1e-12)


@pytest.mark.parametrize("bad", [-1.0, math.nan, math.inf])
def test_bad_dt_and_intensity_raise(bad):
    with pytest.raises(ValueError, match="dt"):
        transition(bad)
    with pytest.raises(ValueError, match="q"):
        process_noise(1.0, bad)


# -- pure predict/update ---------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(6))
def test_predict_update_match_textbook(seed):
    rng = np.random.default_rng(seed)
    x = rng.normal(0, 50, 4)
    P = random_spd(rng, 4, -1, 2)
    R = random_spd(rng, 2, -0.5, 0.5)
    z = rng.normal(0, 50, 2)
    dt, q = rng.uniform(0, 60), 10 ** rng.uniform(-7, -3)
    xp, Pp = predict(x, P, dt, q)
    xn, Pn = naive_predict(x, P, dt, q)
    assert np.allclose(xp, xn, rtol=1e-9, atol=1e-9) and np.allclose(Pp, Pn, rtol=1e-9, atol=1e-9)
    got = update(xp, Pp, z, R)
    want = naive_update(xn, Pn, z, R)
    for g, w in zip(got, want):
        assert np.allclose(g, w, rtol=1e-9, atol=1e-9)


def test_update_with_stacked_measurements_equals_sequential():
    rng = np.random.default_rng(3)
    x, P = rng.normal(0, 5, 4), random_spd(rng, 4, -1, 2)
    z1, z2 = rng.normal(0, 5, 2), rng.normal(0, 5, 2)
    R1, R2 = random_spd(rng, 2, 0, 1), random_spd(rng, 2, 0, 1)
    Rb = np.zeros((4, 4))
    Rb[:2, :2], Rb[2:, 2:] = R1, R2
    joint = update(x, P, np.r_[z1, z2], Rb, np.vstack([H_OFFSET, H_OFFSET]))
    x1, P1 = update(x, P, z1, R1)[:2]
    x2, P2 = update(x1, P1, z2, R2)[:2]
    assert np.allclose(joint.x, x2, rtol=1e-10) and np.allclose(joint.P, P2, rtol=1e-10, atol=1e-12)
    assert joint.nis == pytest.approx(joint_nis(x[:2], psd_sqrt(P[:2, :2]), [z1, z2], [R1, R2]),
                                      rel=1e-10)


def test_huge_prior_takes_the_measurement():
    x, P = np.zeros(4), 1e12 * np.eye(4)
    z, R = np.array([123.4, -56.7]), np.diag([1.0, 4.0])
    res = update(x, P, z, R)
    assert np.allclose(res.x[:2], z, atol=1e-6)
    assert np.allclose(res.P[:2, :2], R, rtol=1e-6)
    assert np.allclose(res.P[2:, 2:], 1e12 * np.eye(2))
    assert_psd(res.P)
    assert res.nis == pytest.approx(z @ z / 1e12, rel=1e-6)


def test_condition_number_1e15_stays_psd():
    rng = np.random.default_rng(11)
    Qm, _ = np.linalg.qr(rng.standard_normal((4, 4)))
    P = Qm @ np.diag([1e12, 1e6, 1.0, 1e-3]) @ Qm.T
    P = 0.5 * (P + P.T)
    x = np.zeros(4)
    for k in range(50):
        x, P = predict(x, P, [0.0, 1.0, 1e5][k % 3], 1e-7)
        x, P = update(x, P, rng.normal(0, 100, 2), 1e-2 * np.eye(2))[:2]
        assert_psd(P)
        assert np.all(np.isfinite(x))


hard_cases = {
    "seed": st.integers(0, 2**32 - 1), "log_lo": st.floats(-6, 2), "span": st.floats(0, 15),
    "dts": st.lists(st.sampled_from([0.0, 1e-6, 0.5, 30.0, 3600.0, 1e5]) | st.floats(0, 1e5),
                    min_size=1, max_size=12),
    "log_r": st.floats(-3, 3), "scale": st.floats(0, 1e6)}


@given(**hard_cases)
@example(seed=911, log_lo=0.0, span=14.349364636316453, dts=[100000.0, 3145.0], log_r=0.0, scale=0.0)
def test_joseph_keeps_covariance_psd(seed, log_lo, span, dts, log_r, scale):
    """Covariance form: symmetric, finite, and PSD to rounding at the largest scale the
    covariance has carried (it cannot resolve anything finer). A prior conditioned 1e14
    predicted over 1e5 s reaches 1e23 nm² on its largest axis; the form's rounding is
    then about 1e-12 of that (the example, found by hypothesis, came out 1.003e-12), so
    the bound allows 1e-11: the square-root form below is the one that keeps precision."""
    rng = np.random.default_rng(seed)
    P = random_spd(rng, 4, log_lo, log_lo + span)
    P = 0.5 * (P + P.T)
    x = rng.normal(0, 1, 4) * scale
    q = 10 ** rng.uniform(-9, 0)
    big = max(1.0, np.linalg.eigvalsh(P)[-1])
    for dt in dts:
        x, P = predict(x, P, dt, q, q_offset=rng.uniform(0, 1e-2))
        big = max(big, np.linalg.eigvalsh(P)[-1])
        assert_psd(P, rel=1e-11 * big / max(1.0, np.linalg.eigvalsh(P)[-1]))
        R = random_spd(rng, 2, log_r, log_r + rng.uniform(0, 2))
        res = update(x, P, rng.normal(0, 1, 2) * scale + x[:2], 0.5 * (R + R.T))
        x, P = res.x, res.P
        assert_psd(P, rel=1e-11 * big / max(1.0, np.linalg.eigvalsh(P)[-1]))
        assert np.all(np.isfinite(x)) and math.isfinite(res.nis) and res.nis >= 0


@given(**hard_cases)
def test_square_root_forms_stay_psd_at_every_scale(seed, log_lo, span, dts, log_r, scale):
    """Square-root form: PSD relative to the covariance's own current scale."""
    rng = np.random.default_rng(seed)
    L = psd_sqrt(random_spd(rng, 4, log_lo, log_lo + span))
    x = rng.normal(0, 1, 4) * scale
    q = 10 ** rng.uniform(-9, 0)
    for dt in dts:
        x, L = predict_sqrt(x, L, dt, q, q_offset=rng.uniform(0, 1e-2))
        assert np.allclose(L, np.tril(L)) and np.all(np.diag(L) >= 0)
        R = random_spd(rng, 2, log_r, log_r + rng.uniform(0, 2))
        res = update_sqrt(x, L, rng.normal(0, 1, 2) * scale + x[:2], 0.5 * (R + R.T))
        x, L = res.x, res.L
        assert_psd(0.5 * (L @ L.T + (L @ L.T).T), rel=1e-12)
        assert np.all(np.isfinite(x)) and math.isfinite(res.nis) and res.nis >= 0
        S = res.S_sqrt @ res.S_sqrt.T
        assert np.linalg.eigvalsh(S)[0] >= 0.99 * np.linalg.eigvalsh(R)[0]


@pytest.mark.parametrize("seed", range(4))
def test_square_root_forms_match_joseph(seed):
    rng = np.random.default_rng(100 + seed)
    x, P = rng.normal(0, 20, 4), random_spd(rng, 4, -1, 2)
    R, z, dt = random_spd(rng, 2, -0.5, 0.5), rng.normal(0, 20, 2), rng.uniform(0, 60)
    xs, L = predict_sqrt(x, psd_sqrt(P), dt, 1e-4)
    xc, Pc = predict(x, P, dt, 1e-4)
    assert np.allclose(xs, xc, rtol=1e-12) and np.allclose(L @ L.T, Pc, rtol=1e-9, atol=1e-12)
    s, c = update_sqrt(xs, L, z, R), update(xc, Pc, z, R)
    assert np.allclose(s.x, c.x, rtol=1e-9, atol=1e-9)
    assert np.allclose(s.L @ s.L.T, c.P, rtol=1e-9, atol=1e-12)
    assert np.allclose(s.S_sqrt @ s.S_sqrt.T, c.S, rtol=1e-12)
    assert s.nis == pytest.approx(c.nis, rel=1e-9)


def test_tria_and_psd_sqrt():
    rng = np.random.default_rng(4)
    M = rng.standard_normal((4, 7))
    L = tria(M)
    assert np.allclose(L, np.tril(L)) and np.all(np.diag(L) >= 0)
    assert np.allclose(L @ L.T, M @ M.T, rtol=1e-12)
    assert np.allclose(tria(M[:, :2]) @ tria(M[:, :2]).T, M[:, :2] @ M[:, :2].T)  # k < n
    singular = np.outer([1.0, 2.0, 0.0, -1.0], [1.0, 2.0, 0.0, -1.0])
    Ls = psd_sqrt(singular)
    assert np.allclose(Ls @ Ls.T, singular, atol=1e-12)
    with pytest.raises(ValueError, match="semidefinite"):
        psd_sqrt(np.diag([1.0, -1.0]))


def _exact_axis(p0: float, q: float, r: float, dts) -> np.ndarray:
    """One axis of the filter in exact rational arithmetic: position measured each step."""
    from fractions import Fraction as Fr

    a, b, d, q, r = Fr(p0), Fr(0), Fr(p0), Fr(q), Fr(r)
    for dt in map(Fr, dts):
        a, b, d = a + 2 * dt * b + dt * dt * d + q * dt**3 / 3, b + dt * d + q * dt**2 / 2, d + q * dt
        s = a + r
        a, b, d = a - a * a / s, b - a * b / s, d - b * b / s
    return np.array([[float(a), float(b)], [float(b), float(d)]])


def test_filter_keeps_full_precision_where_the_covariance_form_cannot():
    """A 1e11 prior tightened by 1e-3 nm² measurements: the covariance must resolve 14
    decades, the square-root factor only 7."""
    p0, q, r, dts = 1e11, 1e-7, 1e-3, [0.0, 30.0, 30.0, 30.0]
    exact = _exact_axis(p0, q, r, dts)
    f = DriftFilter(DriftFilterParams(q=q, min_consensus=0), P0=p0 * np.eye(4))
    x, P, t = np.zeros(4), p0 * np.eye(4), 0.0
    for dt in dts:
        t += dt
        assert f.measure(t, [0.0, 0.0], r * np.eye(2)).accepted
        x, P = predict(x, P, dt, q)
        x, P = update(x, P, np.zeros(2), r * np.eye(2))[:2]
    axis = np.ix_([0, 2], [0, 2])
    assert np.allclose(f.P[axis], exact, rtol=1e-7, atol=0)
    assert np.abs(P[axis] / exact - 1).max() > 100 * np.abs(f.P[axis] / exact - 1).max()


def test_update_survives_a_covariance_whose_rounding_exceeds_R():
    P = np.diag([1e20, 1e20, 1.0, 1.0])
    P[0, 1] = P[1, 0] = 1e20 + 1e5  # indefinite by 1e5 at the 1e20 scale
    res = update(np.zeros(4), P, np.array([3.0, -3.0]), np.eye(2))
    assert np.all(np.isfinite(res.x)) and np.all(np.isfinite(res.P))
    assert math.isfinite(res.nis) and res.nis >= 0


@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 6), log_p0=st.floats(-2, 12),
       log_r=st.floats(-3, 2), moved=st.lists(st.booleans(), min_size=6, max_size=6))
def test_joint_measurements_never_break_the_filter(seed, n, log_p0, log_r, moved):
    rng = np.random.default_rng(seed)
    f = DriftFilter(P0=10.0**log_p0 * np.eye(4))
    for k in range(1, 4):
        zs = rng.normal(0, 10.0 ** (log_r / 2), (n, 2)) + rng.normal(0, 10.0 ** (log_p0 / 2), 2)
        zs[np.array(moved[:n])] += rng.normal(0, 300.0, (int(np.sum(moved[:n])), 2))
        res = f.measure_many(30.0 * k, zs, np.broadcast_to(10.0**log_r * np.eye(2), (n, 2, 2)))
        assert res.dof == 2 * res.accepted.sum()
        if res.accepted.any():
            assert gate(res.joint_nis, res.dof, f.params.gate_probability)
        assert np.all(np.isfinite(f.x))
        assert_psd(f.P, rel=1e-12)


@pytest.mark.parametrize("R", [np.zeros((2, 2)), np.diag([1.0, -1.0]), np.full((2, 2), np.nan)])
def test_update_rejects_bad_R(R):
    with pytest.raises(ValueError, match="R"):
        update(np.zeros(4), np.eye(4), np.zeros(2), R)


def test_update_rejects_bad_shapes():
    with pytest.raises(ValueError, match="z"):
        update(np.zeros(4), np.eye(4), np.zeros(3), np.eye(2))
    with pytest.raises(ValueError, match="P"):
        predict(np.zeros(4), np.eye(3), 1.0, 1.0)


# -- convergence and consistency -------------------------------------------------------------


def test_converges_and_is_consistent():
    speed_err, inside, nees = [], [], []
    for seed in range(5):
        _, rows = run_tracking(seed)
        for t, xt, vt, x, P in rows:
            e = x[:2] - xt
            d2 = e @ np.linalg.solve(P[:2, :2], e)
            inside.append(d2 <= 9.0)  # within 3 sigma
            full = np.r_[e, x[2:] - vt]
            nees.append(full @ np.linalg.solve(P, full))
            if t > 600.0:
                speed_err.append(np.hypot(*(x[2:] - vt)))
    # the true velocity itself wanders by ~3e-3 nm/s between measurements
    assert np.percentile(speed_err, 95) < 0.02
    assert np.sqrt(np.mean(np.square(speed_err))) < 0.012
    assert np.mean(inside) >= 0.95
    # the average NEES of a consistent 4-state filter is 4 (~1200 correlated samples)
    assert 3.4 < np.mean(nees) < 4.6


def test_constant_drift_velocity_converges():
    _, rows = run_tracking(0, w=0.0)
    err = np.array([np.hypot(*(x[2:] - vt)) for t, _, vt, x, _ in rows])
    times = np.array([r[0] for r in rows])
    assert err[times > 300.0].max() < 0.02
    assert err[times > 3600.0].max() < 0.002


def test_velocity_estimate_is_close_after_ten_minutes():
    _, rows = run_tracking(42, t_end=900.0)
    late = [np.hypot(*(x[2:] - vt)) for t, _, vt, x, _ in rows if t > 600.0]
    assert late and max(late) < 0.02


def test_long_gap_keeps_everything_finite():
    f = DriftFilter(epoch=5.0)
    f.measure(10.0, [1.0, 2.0])
    f.predict_to(10.0 + 1e5)
    assert_psd(f.P)
    res = f.measure(10.0 + 1e5 + 1.0, [3e4, -2e4])
    assert res.accepted  # a 1e5 s gap leaves ~10 µm of uncertainty
    assert_psd(f.P)
    assert np.all(np.isfinite(f.x))


# -- gating ----------------------------------------------------------------------------------


def test_gate_threshold_closed_form():
    for p in (0.9, 0.99, 0.997):
        assert gate_threshold(2, p) == pytest.approx(-2.0 * math.log(1.0 - p), rel=1e-10)
    assert gate(11.6, 2, 0.997) and not gate(11.7, 2, 0.997)
    with pytest.raises(ValueError, match="p"):
        gate_threshold(2, 1.0)
    with pytest.raises(ValueError, match="dof"):
        gate_threshold(0, 0.9)


def test_gate_rejects_a_50nm_jump_and_accepts_normal_measurements():
    rng = np.random.default_rng(7)
    f = DriftFilter(DriftFilterParams(q=2.5e-7))
    v = np.array([0.3, -0.1])
    accepted = []
    for k in range(1, 120):
        t = 30.0 * k
        accepted.append(f.measure(t, v * t + rng.normal(0, 1.5, 2), 2.25 * np.eye(2)).accepted)
    assert np.mean(accepted) >= 0.97
    t = 30.0 * 120
    x_pred, P_pred = f.state_at(t)
    res = f.measure(t, v * t + np.array([50.0, 0.0]), 2.25 * np.eye(2), label="p7")
    assert not res.accepted and res.reason == "gated" and res.label == "p7"
    assert res.nis > res.threshold
    assert np.array_equal(f.x, x_pred) and np.array_equal(f.P, P_pred)
    assert f.measurements[-1] is res
    ok = f.measure(t + 30.0, v * (t + 30.0) + rng.normal(0, 1.5, 2), 2.25 * np.eye(2))
    assert ok.accepted


def converged_filter(v=(0.3, -0.1)):
    rng = np.random.default_rng(5)
    f = DriftFilter(DriftFilterParams(q=2.5e-7))
    v = np.asarray(v)
    for k in range(1, 60):
        f.measure(30.0 * k, v * 30.0 * k + rng.normal(0, 1.0, 2), np.eye(2))
    return f, v, rng


def test_joint_measurement_flags_the_object_that_moved():
    f, v, rng = converged_filter()
    t = 30.0 * 60
    zs = v * t + rng.normal(0, 1.0, (4, 2))
    zs[2] += [0.0, 50.0]
    res = f.measure_many(t, zs, np.broadcast_to(np.eye(2), (4, 2, 2)), labels="abcd")
    assert res.accepted.tolist() == [True, True, False, True]
    assert res.results[2].reason == "outlier" and res.results[2].label == "c"
    assert not res.drift_jump and res.dof == 6
    assert abs(f.x[1] - v[1] * t) < 3.0


def test_consistent_majority_is_a_drift_jump():
    f, v, rng = converged_filter()
    t = 30.0 * 60
    zs = v * t + np.array([40.0, -25.0]) + rng.normal(0, 1.0, (3, 2))
    lone = DriftFilter(f.params, x0=f.x, P0=f.P, epoch=f.time)
    assert not lone.measure(t, zs[0], np.eye(2)).accepted
    res = f.measure_many(t, zs, np.broadcast_to(np.eye(2), (3, 2, 2)))
    assert res.drift_jump and res.accepted.all()
    assert np.allclose(f.x[:2], v * t + [40.0, -25.0], atol=3.0)
    no_jump = DriftFilter(DriftFilterParams(q=2.5e-7, min_consensus=0), x0=lone.x, P0=lone.P,
                          epoch=lone.time)
    assert not no_jump.measure_many(t, zs, np.broadcast_to(np.eye(2), (3, 2, 2))).accepted.any()


def test_select_consistent_pure():
    R = np.broadcast_to(np.eye(2), (3, 2, 2))
    zs = np.array([[0.5, 0.0], [-0.5, 0.3], [0.1, -0.4]])
    sel = select_consistent(np.zeros(2), np.eye(2), zs, R)
    assert sel.accepted.all() and not sel.drift_jump and np.all(sel.jump == 0)
    assert sel.joint_nis == pytest.approx(joint_nis(np.zeros(2), np.eye(2), zs, R))
    # joint NIS = the stacked textbook form
    S = np.kron(np.ones((3, 3)), np.eye(2)) + np.eye(6)
    v = zs.reshape(-1)
    assert sel.joint_nis == pytest.approx(v @ np.linalg.solve(S, v), rel=1e-12)
    mean, cov, spread = weighted_mean(zs, R)
    assert np.allclose(mean, zs.mean(axis=0)) and np.allclose(cov, np.eye(2) / 3)
    assert spread == pytest.approx(((zs - zs.mean(axis=0)) ** 2).sum())
    m, L = fuse(np.zeros(2), 1e6 * np.eye(2), zs, R)
    assert np.allclose(m, mean, atol=1e-9) and np.allclose(L @ L.T, cov, atol=1e-9)
    # a singular prior (offset known exactly) takes no notice of the measurements
    m0, L0 = fuse(np.array([1.0, 2.0]), np.zeros((2, 2)), zs, R)
    assert np.allclose(m0, [1.0, 2.0]) and np.allclose(L0, 0.0)


# -- creep -----------------------------------------------------------------------------------


def test_creep_closed_form_and_rate():
    times, steps = np.array([0.0, 10.0]), np.array([[1000.0, 0.0], [0.0, -2000.0]])
    got = creep_offset(20.0, times, steps, 0.02, 1.0)
    want = -0.02 * (math.log10(21.0) * steps[0] + math.log10(11.0) * steps[1])
    assert np.allclose(got, want, rtol=1e-14)
    assert np.allclose(creep_offset(5.0, times, steps, 0.02, 1.0),
                       -0.02 * math.log10(6.0) * steps[0])
    h = 1e-5  # rate is the derivative of the creep length
    rate = creep_rate(20.0, times, steps, 0.02, 1.0)
    d0 = 0.02 * 1000.0 * (math.log10(1 + (20 + h)) - math.log10(1 + (20 - h))) / (2 * h)
    assert rate[0] == pytest.approx(d0, rel=1e-6)


def test_creep_sign_matches_the_simulated_world():
    from nanoasm.world.sim import DriftModel
    from nanoasm.world.params import CreepParams, DriftParams

    world = DriftModel(DriftParams(velocity=(0.0, 0.0), random_walk=0.0),
                       CreepParams(amplitude=0.02, tau=0.5, min_step=100.0),
                       np.random.default_rng(0))
    hist = CreepHistory(CreepModelParams(amplitude=0.02, tau=0.5, min_step=100.0))
    for t, s in ((1.0, (3000.0, -500.0)), (4.0, (-800.0, 1200.0)), (5.0, (50.0, 0.0))):
        assert world.record_move(t, *s) == hist.record(t, s)
    for t in (0.5, 2.0, 7.5, 100.0):
        assert np.allclose(hist.offset(t), world.offset(t), rtol=1e-12, atol=1e-12)


def test_creep_history_prunes_continuously():
    p = CreepModelParams(amplitude=0.02, tau=1.0, min_step=500.0, rate_tol=1e-2, max_moves=3)
    hist = CreepHistory(p)
    assert not hist.record(0.0, (100.0, 0.0))  # too short
    assert hist.record(0.0, (5000.0, 0.0))
    t_slow = 0.02 * 5000.0 / (math.log(10.0) * 1e-2) - 1.0 + 0.5  # the rate just fell below rate_tol
    before = hist.offset(t_slow)
    assert hist.prune(t_slow - 10.0) == 0 and hist.prune(t_slow) == 1
    assert len(hist) == 0 and np.allclose(hist.offset(t_slow), before, rtol=1e-8)
    for t in (2.0 * t_slow, 50.0 * t_slow):  # a frozen move goes on creeping
        exact = creep_offset(t, np.array([0.0]), np.array([[5000.0, 0.0]]), 0.02, 1.0)
        assert np.allclose(hist.offset(t), exact, rtol=1e-8) and not np.allclose(exact, before, rtol=1e-3)
    for k in range(5):
        hist.record(t_slow + k, (0.0, 1000.0))
    assert len(hist) == 3  # the two oldest were frozen
    with pytest.raises(ValueError, match="time order"):
        hist.record(0.0, (1000.0, 0.0))


def test_creep_history_takes_a_rounding_apart_as_the_same_time():
    """5078.923 after 5078.923000000001 (the same instant summed in another order) was
    refused and stopped a 1000-object dry-run; a millisecond before still is refused."""
    hist = CreepHistory(CreepModelParams(amplitude=0.02, tau=1.0, min_step=500.0))
    assert hist.record(5078.923000000001, (1000.0, 0.0))
    assert hist.record(5078.923, (0.0, 1000.0))
    np.testing.assert_array_equal(hist.times, [5078.923000000001] * 2)
    with pytest.raises(ValueError, match="time order"):
        hist.record(5078.922, (1000.0, 0.0))


def _creep_run(model: CreepModelParams, seed: int = 0):
    """Converge, make a 5.4 µm move, and measure every 5 s; truth creeps with c = 0.02.

    Returns the RMS offset error (nm) after the move, the number of rejected
    measurements and the fraction of steps whose error lies within 3 σ of the filter's
    offset covariance."""
    true = CreepModelParams(amplitude=0.02, tau=1.0)
    rng = np.random.default_rng(seed)
    v = np.array([0.3, -0.1])
    f = DriftFilter(DriftFilterParams(q=2.5e-7, creep=model))
    truth_creep = CreepHistory(true)
    t_move, step = 1800.0, np.array([5000.0, 2000.0])
    errors, inside, rejected = [], [], 0
    for t in np.r_[np.arange(30.0, t_move, 30.0), t_move + np.arange(2.0, 302.0, 5.0)]:
        if t > t_move and len(truth_creep) == 0:
            truth_creep.record(t_move, step)
            f.record_move(t_move, step)
        truth = v * t + truth_creep.offset(t)
        res = f.measure(t, truth + rng.normal(0, 1.0, 2), np.eye(2))
        if t > t_move:
            rejected += not res.accepted
            est = f.offset(t)
            e = est.offset - truth
            errors.append(np.hypot(*e))
            inside.append(e @ np.linalg.solve(est.cov, e) <= 9.0)
    return float(np.sqrt(np.mean(np.square(errors)))), rejected, float(np.mean(inside))


def test_creep_term_tracks_a_large_move_better():
    with_creep, rej_with, _ = _creep_run(CreepModelParams(amplitude=0.02, tau=1.0))
    without, rej_without, _ = _creep_run(CreepModelParams(amplitude=0.0, tau=1.0))
    assert with_creep < 1.5 and rej_with <= 1
    assert without > 5.0 * with_creep and rej_without > 10


def test_uncertain_creep_amplitude_widens_instead_of_gating():
    _, rejected, covered = _creep_run(CreepModelParams(amplitude=0.015, tau=1.0))
    assert rejected > 10 and covered < 0.5  # a 25 % amplitude error gates everything out
    err, rejected, covered = _creep_run(CreepModelParams(amplitude=0.015, tau=1.0,
                                                         amplitude_std=0.005))
    assert rejected <= 1 and covered >= 0.95
    exact, _, _ = _creep_run(CreepModelParams(amplitude=0.02, tau=1.0, amplitude_std=0.005))
    assert exact < 2.0 < err


# -- smoother --------------------------------------------------------------------------------


def test_rts_matches_textbook_form():
    rng = np.random.default_rng(2)
    f = DriftFilter(DriftFilterParams(q=1e-4))
    for k in range(1, 15):
        f.measure(10.0 * k, rng.normal(0, 5, 2), np.eye(2) * rng.uniform(1, 4))
    s = smooth(f.history)
    xs, Ps = s.x[-1].copy(), s.P[-1].copy()
    H = f.history
    for k in range(len(H) - 2, -1, -1):
        F = transition(H[k + 1].dt)
        Pp = F @ H[k].P @ F.T + H[k + 1].Q_sqrt @ H[k + 1].Q_sqrt.T
        C = H[k].P @ F.T @ np.linalg.inv(Pp)
        xs = H[k].x + C @ (xs - F @ H[k].x)
        Ps = H[k].P + C @ (Ps - Pp) @ C.T
        assert np.allclose(s.x[k], xs, rtol=1e-9, atol=1e-9)
        assert np.allclose(s.P[k], Ps, rtol=1e-8, atol=1e-9)


def test_smoother_beats_the_filter():
    f_err, s_err = [], []
    for seed in range(4):
        f, rows = run_tracking(seed, t_end=3600.0)
        track = smooth(f.history)
        by_t = {round(h.t, 6): i for i, h in enumerate(f.history)}
        for t, xt, _, x, P in rows:
            i = by_t[round(t, 6)]
            f_err.append(np.sum((x[:2] - xt) ** 2))
            s_err.append(np.sum((track.offset[i] - xt) ** 2))
            assert np.trace(track.P[i]) <= np.trace(P) * (1 + 1e-9)
            assert_psd(track.P[i], rel=1e-8)
    assert np.mean(s_err) < 0.8 * np.mean(f_err)


def test_rts_survives_singular_predictions():
    xs = np.zeros((3, 4))
    Ls = np.zeros((3, 4, 4))
    xs_s, Ls_s = rts(xs, Ls, xs, Ls, [np.zeros((4, 1))] * 3, np.array([0.0, 0.0, 0.0]))
    assert np.all(np.isfinite(xs_s)) and np.all(Ls_s == 0)


# -- the stateful filter ---------------------------------------------------------------------


def test_offset_is_read_only_and_r_max_grows():
    f, _, _ = converged_filter()
    x, P, n = f.x, f.P, len(f.history)
    est = f.offset(f.time + 100.0)
    assert np.array_equal(f.x, x) and np.array_equal(f.P, P) and len(f.history) == n
    xp, Pp = f.state_at(f.time + 100.0)
    assert np.allclose(est.offset, xp[:2]) and np.allclose(est.cov, Pp[:2, :2])
    r_now, r_later = f.r_max(f.time), f.r_max(f.time + 3600.0)
    assert r_now == pytest.approx(3 * math.sqrt(np.linalg.eigvalsh(f.P[:2, :2])[-1]))
    assert r_now < 3.0 < r_later
    assert f.r_max(f.time, k=1.0) == pytest.approx(r_now / 3)
    with pytest.raises(ValueError, match="precedes"):
        f.predict_to(f.time - 1.0)


def test_offset_includes_creep():
    f = DriftFilter(DriftFilterParams(creep=CreepModelParams(amplitude=0.02, tau=1.0)))
    assert f.record_move(0.0, (1000.0, 0.0))
    assert np.allclose(f.offset(9.0).offset, [-0.02 * 1000.0, 0.0])


def test_epoch_keeps_precision_at_1e7_seconds():
    f0, _ = run_tracking(9, t_end=1800.0, epoch=0.0)
    f1, _ = run_tracking(9, t_end=1800.0, epoch=1.234e7)
    assert np.allclose(f0.x, f1.x, rtol=1e-9, atol=1e-9)
    assert np.allclose(f0.P, f1.P, rtol=1e-9, atol=1e-12)
    assert f1.time - 1.234e7 == pytest.approx(f0.time, abs=1e-8)


def test_deterministic():
    a, _ = run_tracking(3, t_end=1800.0)
    b, _ = run_tracking(3, t_end=1800.0)
    assert np.array_equal(a.x, b.x) and np.array_equal(a.P, b.P)
    sa, sb = smooth(a.history), smooth(b.history)
    assert np.array_equal(sa.x, sb.x) and np.array_equal(sa.P, sb.P)


def test_inflate_widens_and_is_smoothable():
    f, _, _ = converged_filter()
    before = f.r_max(f.time)
    f.inflate(offset_std=20.0)
    assert f.r_max(f.time) > 50.0 > before
    assert_psd(smooth(f.history).P[-2], rel=1e-8)


@pytest.mark.parametrize(("kwargs", "name"), [
    ({"q": -1.0}, "q"), ({"offset_std": 0.0}, "offset_std"), ({"velocity_std": math.nan}, "velocity_std"),
    ({"measurement_std": -2.0}, "measurement_std"), ({"gate_probability": 1.0}, "gate_probability"),
    ({"min_consensus": -1}, "min_consensus"), ({"min_consensus": 1.5}, "min_consensus"),
])
def test_filter_params_are_validated(kwargs, name):
    with pytest.raises(ValueError, match=name):
        DriftFilterParams(**kwargs)


def test_filter_params_reject_a_wrong_creep_type():
    with pytest.raises(TypeError, match="creep"):
        DriftFilterParams(creep=0.02)


@pytest.mark.parametrize(("kwargs", "name"), [
    ({"amplitude": -0.1}, "amplitude"), ({"tau": 0.0}, "tau"), ({"min_step": math.inf}, "min_step"),
    ({"rate_tol": 0.0}, "rate_tol"), ({"max_moves": 0}, "max_moves"),
])
def test_creep_params_are_validated(kwargs, name):
    with pytest.raises(ValueError, match=name):
        CreepModelParams(**kwargs)


def test_measure_rejects_bad_input():
    f = DriftFilter()
    with pytest.raises(ValueError, match="Rs"):
        f.measure(1.0, [0.0, 0.0], np.diag([1.0, -1.0]))
    with pytest.raises(ValueError, match="zs"):
        f.measure(1.0, [math.nan, 0.0])
    with pytest.raises(ValueError, match="labels"):
        f.measure_many(1.0, [[0.0, 0.0]], labels=["a", "b"])
    assert len(f.history) == 1


@given(seed=st.integers(0, 2**32 - 1),
       gaps=st.lists(st.sampled_from([0.0, 1e-3, 1.0, 30.0, 1e4, 1e5]), min_size=2, max_size=10),
       log_r=st.floats(-4, 3), log_p0=st.floats(0, 12))
def test_smoother_covariance_stays_psd(seed, gaps, log_r, log_p0):
    rng = np.random.default_rng(seed)
    f = DriftFilter(DriftFilterParams(q=10 ** rng.uniform(-9, -2), min_consensus=0),
                    P0=10.0**log_p0 * np.eye(4))
    t = 0.0
    for gap in gaps:
        t += gap
        f.measure(t, rng.normal(0, 100, 2), 10.0**log_r * np.eye(2))
    track = smooth(f.history)
    assert np.all(np.isfinite(track.x))
    for P in track.P:
        assert_psd(P, rel=1e-8)


# -- recovering from a drift jump seen by lone measurements ------------------------------------


def _lone_run(jump_at: float, jump, labels, t_end: float = 2400.0, *, velocity_change=(0.0, 0.0)):
    """Lone offsets every 60 s of a drift that jumps by ``jump`` (nm) and changes velocity
    by ``velocity_change`` (nm/s) at ``jump_at``; returns the filter, results and truth."""
    rng = np.random.default_rng(21)
    v = np.array([0.3, -0.1])
    f = DriftFilter(DriftFilterParams(q=2.5e-7))
    out = []
    for k, t in enumerate(np.arange(60.0, t_end, 60.0)):
        truth = v * t + (t >= jump_at) * (np.asarray(jump) + np.asarray(velocity_change) * (t - jump_at))
        res = f.measure_many(t, [truth + rng.normal(0, 1.0, 2)], np.eye(2)[None],
                             labels=[labels(k)])
        out.append((t, res, truth))
    return f, out


def test_lone_measurements_recover_from_a_drift_jump():
    f, out = _lone_run(1200.0, (40.0, -25.0), labels=lambda k: f"p{k}")
    at = [i for i, (t, _, _) in enumerate(out) if t >= 1200.0][0]
    first, second = out[at][1], out[at + 1][1]
    assert not first.accepted[0] and first.results[0].reason == "gated"
    assert second.drift_jump and second.accepted[0] and second.results[0].drift_jump
    assert len(second.readmitted) == 1 and second.readmitted[0].label == f"p{at}"
    assert second.readmitted[0].accepted and second.readmitted[0].t == out[at][0]
    t_end, res, truth = out[-1]
    assert res.accepted.all() and np.hypot(*(f.offset(t_end).offset - truth)) < 3.0
    times = [h.t for h in f.history]
    assert times == sorted(times)
    assert [h.kind for h in f.history].count("measure") == len(out)  # the rejection was replaced
    track = smooth(f.history)
    assert all(np.linalg.eigvalsh(P)[0] >= -1e-9 for P in track.P)


def test_lone_measurements_recover_from_a_velocity_change():
    f, out = _lone_run(1200.0, (0.0, 0.0), labels=lambda k: f"p{k}", t_end=4800.0,
                       velocity_change=(0.0, 0.12))
    late = [np.hypot(*(res.results[0].innovation)) for t, res, _ in out if t > 2400.0]
    assert all(res.accepted.all() for t, res, _ in out if t > 2400.0)
    assert max(late) < 6.0
    assert abs(f.x[3] - (-0.1 + 0.12)) < 0.02


def test_the_same_object_twice_is_not_a_drift_jump():
    _, out = _lone_run(1200.0, (40.0, -25.0), labels=lambda k: "p0", t_end=1400.0)
    assert not any(res.accepted[0] for t, res, _ in out if t >= 1200.0)


def test_objects_moving_different_ways_are_not_a_drift_jump():
    f, v, rng = converged_filter()
    t = 30.0 * 60
    a = f.measure(t, v * t + [45.0, 0.0], np.eye(2), label="a")
    b = f.measure(t + 30.0, v * (t + 30.0) + [0.0, -45.0], np.eye(2), label="b")
    assert not a.accepted and not b.accepted and not b.drift_jump
    c = f.measure(t + 60.0, v * (t + 60.0) + rng.normal(0, 1.0, 2), np.eye(2), label="c")
    assert c.accepted and not c.drift_jump


def test_creeping_offset_follows_recorded_and_pending_moves():
    """The DAC's drift prediction: thermal line plus the exact creep of recent moves,
    old moves as a line through their value and rate (error under 0.2 nm over 5 s)."""
    from nanoasm.drift.creep import CreepingOffset, creep_offset

    p = CreepModelParams(amplitude=0.01, tau=0.1, min_step=500.0)
    hist = CreepHistory(p)
    moves = [(10.0, (2000.0, 0.0)), (80.0, (-1500.0, 900.0)), (118.0, (700.0, -600.0))]
    for t, s in moves:
        hist.record(t - 5.0, s)               # the history counts from an epoch 5 s later
    pending = [(121.0, (0.0, 1200.0))]
    pred = CreepingOffset((3.0, -2.0), (0.3, -0.2), 120.0, hist, epoch=5.0, pending=pending)
    ts = np.linspace(120.0, 125.0, 51)
    every = moves + pending
    exact = np.array([creep_offset(t, [m[0] for m in every], [m[1] for m in every], 0.01, 0.1) for t in ts])
    thermal = np.array([3.0, -2.0]) + (ts - 120.0)[:, None] * np.array([0.3, -0.2])
    got = pred(ts)
    assert got.shape == (51, 2) and np.isfinite(got).all()
    assert np.abs(got - (thermal + exact)).max() < 0.2
    # the pending travel's creep starts when it ends, not before
    assert np.allclose(pred(np.array([120.5]))[0] - thermal[5],
                       creep_offset(120.5, [m[0] for m in moves], [m[1] for m in moves], 0.01, 0.1),
                       atol=0.2)
    # later records do not change a prediction already made
    hist.record(130.0, (5000.0, 0.0))
    assert np.array_equal(pred(ts), got)


# -- fixed features and relocalisation -------------------------------------------------------


def test_projected_measurement_along_both_axes_is_an_offset_measurement():
    a, _, _ = converged_filter()
    b, _, _ = converged_filter()
    z, R = np.array([541.0, -181.5]), np.diag([2.0, 3.0])
    full = a.measure(1800.0, z, R)
    proj = b.measure_projected(1800.0, z, np.eye(2), R)
    assert full.accepted and proj.accepted
    assert np.allclose(a.x, b.x, atol=1e-9) and np.allclose(a.P, b.P, atol=1e-9)
    assert proj.directions.shape == (2, 2) and full.directions is None


def test_an_edge_informs_only_the_coordinate_normal_to_it():
    f, v, _ = converged_filter()
    f.inflate(offset_std=20.0)          # both axes uncertain, independent of the velocity
    before = f.offset(1800.0)
    n = np.array([0.6, 0.8])
    truth = v * 1800.0 + np.array([8.0, -3.0])
    m = f.measure_projected(1800.0, [n @ truth, n @ truth], np.vstack([n, n]), np.eye(2) * 0.25)
    after = f.offset(1800.0)
    assert m.accepted and m.innovation.shape == (2,)
    t = np.array([-0.8, 0.6])
    assert n @ after.cov @ n < 0.2 * (n @ before.cov @ n)          # normal: measured
    assert t @ after.cov @ t > 0.9 * (t @ before.cov @ t)          # along the edge: not
    assert abs(n @ (after.offset - truth)) < 1.0


def test_a_projected_measurement_far_off_is_gated_and_only_predicts():
    f, v, _ = converged_filter()
    x_prior, P_prior = f.state_at(1800.0)
    m = f.measure_projected(1800.0, [(v * 1800.0)[0] + 60.0], [[1.0, 0.0]], [[1.0]])
    assert not m.accepted and m.reason == "gated" and m.nis > m.threshold
    assert np.allclose(f.x, x_prior) and np.allclose(f.P, P_prior)
    assert f.history[-1].kind == "measure" and f.time == 1800.0


def test_a_projected_measurement_takes_the_creep_out():
    f = DriftFilter(DriftFilterParams(q=1e-6, creep=CreepModelParams(amplitude=0.01, tau=0.1)))
    f.record_move(10.0, (4000.0, 0.0))
    creep = f.creep.offset(20.0)
    assert creep[0] < -10.0
    m = f.measure_projected(20.0, [creep[0] + 3.0], [[1.0, 0.0]], [[1.0]])
    assert m.accepted and abs(m.innovation[0] - 3.0) < 1e-9
    assert abs(f.offset(20.0).offset[0] - (creep[0] + 3.0)) < 1.0


@pytest.mark.parametrize("bad", [dict(z=[1.0], directions=[[1.0, 1.0]]),
                                 dict(z=[1.0, 2.0], directions=[[1.0, 0.0]]),
                                 dict(z=[np.nan], directions=[[1.0, 0.0]]),
                                 dict(z=[1.0], directions=[[1.0, 0.0]], R=[[-1.0]])])
def test_projected_measurement_rejects_bad_input(bad):
    with pytest.raises(ValueError):
        DriftFilter().measure_projected(1.0, **bad)


def test_reinitialise_sets_the_offset_and_keeps_the_velocity():
    f, v, _ = converged_filter()
    vel = f.x[2:]
    f.reinitialise(1800.0, v * 1800.0 + [300.0, -120.0], np.diag([9.0, 4.0]), velocity_std=0.01)
    est = f.offset(1800.0)
    assert np.allclose(est.offset, v * 1800.0 + [300.0, -120.0])
    assert np.allclose(est.cov, np.diag([9.0, 4.0]))
    assert np.allclose(f.x[2:], vel) and f.P[2, 2] >= 1e-4
    assert np.allclose(f.P[:2, 2:], 0.0) and f.history[-1].kind == "reset"
    m = f.measure(1830.0, v * 1830.0 + [300.0, -120.0], np.eye(2))
    assert m.accepted


# -- static parameters: what a reference image carried ---------------------------------------
def _image_filter(t0=1000.0):
    """A filter with two static parameters: the velocity ``w`` while a reference image was
    scanned (image row of time τ shows a point displaced by ``w τ``), known to 0.05 nm/s."""
    v = np.array([0.3, -0.2])
    P0 = np.diag([4.0, 4.0, 0.05**2, 0.05**2, 0.05**2, 0.05**2])
    P0[2:4, 4:] = P0[4:, 2:4] = np.eye(2) * 0.05**2          # one velocity, then and now
    x0 = np.concatenate([v * t0 + [3.0, -4.0], v + [0.04, -0.03], v + [0.04, -0.03]])
    return DriftFilter(DriftFilterParams(q=1e-8, q_offset=1e-6), x0=x0, P0=P0, statics=2, start=t0), v


def test_static_parameters_learn_what_the_reference_image_carried_and_stay_consistent():
    f, v = _image_filter()
    rng = np.random.default_rng(3)
    taus = rng.uniform(0.0, 1000.0, 12)                 # twelve references on different rows
    nis = []
    for k in range(240):
        t = 1000.0 + 20.0 * (k + 1)
        tau = taus[k % 12]
        n = np.array([[1.0, 0.0]]) if k % 2 else np.array([[0.0, 1.0]])
        truth = n @ (v * t) - n @ (v * tau) + rng.normal(0.0, 1.0, 1)
        m = f.measure_projected(t, truth, n, [[1.0]], static=-tau * n)
        nis.append(m.nis)
    assert np.allclose(f.x[4:], v, atol=0.004) and np.allclose(f.x[2:4], v, atol=0.004)
    assert abs(np.mean(nis) - 1.0) < 0.35                 # one dof, consistent throughout
    mean, cov = f.projected(f.time, np.eye(2), static=-500.0 * np.eye(2))
    assert np.allclose(mean, v * f.time - v * 500.0, atol=3.0) and np.all(np.isfinite(cov))


def test_forget_offset_lets_the_next_measurement_place_it_and_keeps_the_rest():
    f, v = _image_filter()
    f.measure_projected(1010.0, v * 1010.0 - v * 200.0, np.eye(2), np.eye(2), static=-200.0 * np.eye(2))
    statics, vel = f.x[4:], f.x[2:4]
    f.forget_offset(1020.0, 1000.0)
    assert np.allclose(f.P[:2, :2], np.eye(2) * 1e6) and np.allclose(f.P[:2, 2:], 0.0)
    assert np.allclose(f.x[4:], statics) and np.allclose(f.x[2:4], vel)
    jumped = v * 1030.0 + [300.0, -200.0]
    m = f.measure_projected(1030.0, jumped - v * 100.0, np.eye(2), np.eye(2), static=-100.0 * np.eye(2))
    assert m.accepted and np.allclose(f.offset(1030.0).offset, jumped, atol=6.0)


def test_a_filter_with_statics_round_trips_and_refuses_whole_offset_batches():
    f, v = _image_filter()
    f.measure_projected(1010.0, v * 1010.0, np.eye(2), np.eye(2), static=np.zeros((2, 2)))
    back = DriftFilter.from_state(f.params, f.state_dict())
    assert back.statics == 2 and np.allclose(back.x, f.x) and np.allclose(back.P, f.P)
    with pytest.raises(ValueError, match="measure_projected"):
        f.measure(1020.0, v * 1020.0)
    with pytest.raises(ValueError, match="static"):
        f.measure_projected(1020.0, [1.0], [[1.0, 0.0]], [[1.0]], static=np.zeros((1, 3)))


def _creep_truth(amplitude, moves, t):
    return creep_offset(t, [m[0] for m in moves], [m[1] for m in moves], amplitude, 0.1)


def test_a_filter_learns_the_creep_amplitude_it_was_wrong_about():
    """Truth creeps 30 % more than nominal; a 3 µm move a minute, offsets measured every
    20 s with 1 nm noise. Learning the amplitude beats treating its error as noise."""
    rng = np.random.default_rng(8)
    nominal = CreepModelParams(amplitude=0.01, tau=0.1, amplitude_std=0.003, rate_tol=1e-6)
    runs = {}
    for learn in (False, True):
        f = DriftFilter(DriftFilterParams(q=1e-8, q_offset=1e-4, creep=nominal), learn_creep=learn,
                        x0=np.zeros(4), P0=np.diag([1.0, 1.0, 1e-4, 1e-4]))
        moves, errs, nis = [], [], []
        for k in range(1, 90):
            t = 20.0 * k
            if k % 3 == 0:
                step = np.array([3000.0, 0.0]) * (1 if k % 6 else -1)
                moves.append((t - 1.0, step))
                f.record_move(t - 1.0, step)
            truth = _creep_truth(0.013, moves, t)
            m = f.measure(t, truth + rng.normal(0, 1.0, 2), np.eye(2)) if not learn else \
                f.measure_projected(t, truth + rng.normal(0, 1.0, 2), np.eye(2), np.eye(2))
            nis.append(m.nis)
            errs.append(np.hypot(*(f.offset(t + 19.0).offset - _creep_truth(0.013, moves, t + 19.0))))
        runs[learn] = (f, np.sqrt(np.mean(np.square(errs[30:]))), np.mean(nis[30:]))
    f, err_learnt, nis_learnt = runs[True]
    assert abs(f.x[-1] - 0.003) < 0.0005                  # the amplitude's error, learnt
    assert err_learnt < 0.5 * runs[False][1]
    assert nis_learnt < 4.0
    back = DriftFilter.from_state(f.params, f.state_dict())
    assert back.learn_creep and np.allclose(back.x, f.x)
    assert np.allclose(back.offset(2000.0).offset, f.offset(2000.0).offset)


def test_information_is_the_offsets_trace_reduction_a_measurement_would_bring():
    f = DriftFilter(DriftFilterParams(q=0.0, q_offset=0.0), x0=np.zeros(4), P0=np.diag([100.0, 25.0, 1e-9, 1e-9]))
    R = np.eye(2) * 4.0
    assert f.information(0.0, np.eye(2), R) == pytest.approx(100 - 400 / 104 + 25 - 100 / 29)
    assert f.information(0.0, [[1.0, 0.0]], [[4.0]]) == pytest.approx(100 - 400 / 104)   # an edge: x alone
    assert f.information(0.0, [[0.0, 1.0]], [[4.0]]) == pytest.approx(25 - 100 / 29)
    before = f.offset(0.0).cov
    f.measure_projected(0.0, [0.0], [[1.0, 0.0]], [[4.0]])
    assert np.trace(before) - np.trace(f.offset(0.0).cov) == pytest.approx(100 - 400 / 104)


def test_the_creep_amplitude_error_may_come_with_the_prior_correlated():
    """x0 one longer than 4 + statics: δc's prior is given with the rest (correlated),
    not appended with ``creep.amplitude_std``."""
    nominal = CreepModelParams(amplitude=0.01, tau=0.1, amplitude_std=0.003)
    P0 = np.diag([4.0, 4.0, 1e-4, 1e-4, 1e-2, 4e-6])
    P0[0, 5] = P0[5, 0] = 0.003           # the offset's error goes with δc's
    f = DriftFilter(DriftFilterParams(creep=nominal), x0=np.array([1, 2, 0, 0, 0.1, 0.001]), P0=P0,
                    statics=1, learn_creep=True)
    assert f.statics == 2 and f.x.shape == (6,) and f.x[-1] == pytest.approx(0.001)
    np.testing.assert_allclose(f.P, P0, atol=1e-12)
    f.record_move(0.0, (5000.0, 0.0))
    # a measurement of δc's own effect beyond the creep now (the extra column) moves δc
    before, S = f.x[-1], np.array([[0.0, 500.0]])
    mean, _ = f.projected(10.0, [[1.0, 0.0]], S)
    m = f.measure_projected(10.0, mean + 3.0, [[1.0, 0.0]], [[1.0]], static=S)
    after, _ = f.projected(10.0, [[1.0, 0.0]], S)
    assert m.accepted and f.x[-1] != before and abs(after - (mean + 3.0)) < 1.0
    with pytest.raises(ValueError, match="static"):
        f.measure_projected(20.0, [0.0], [[1.0, 0.0]], [[1.0]], static=np.zeros((1, 3)))
    back = DriftFilter.from_state(f.params, f.state_dict())
    assert back.statics == 2 and np.allclose(back.x, f.x) and np.allclose(back.P, f.P)


def test_a_long_move_widens_the_offset_along_its_step_for_the_creep_time_constant():
    """An error of τ leaves c s δ(ln τ) / ln 10 along a step s once the move has crept a
    while: with tau_std, each recorded move adds that much variance along its step, at
    the filter's present time; a short move (no creep) and tau_std = 0 add none."""
    creep = CreepModelParams(amplitude=0.01, tau=0.1, min_step=500.0, tau_std=0.25)
    f = DriftFilter(DriftFilterParams(creep=creep), x0=np.zeros(4), P0=np.diag([4.0, 4.0, 1e-4, 1e-4]))
    before, t0 = f.P.copy(), f.time
    assert f.record_move(10.0, (6000.0, 8000.0))
    grow = (0.01 * 0.25 * 10000.0 / math.log(10.0)) ** 2           # 10.9 nm, squared
    u = np.array([0.6, 0.8])
    assert u @ f.P[:2, :2] @ u == pytest.approx(4.0 + grow)
    v = np.array([-0.8, 0.6])
    assert v @ f.P[:2, :2] @ v == pytest.approx(4.0)
    assert f.time == t0 and np.allclose(f.P[2:, 2:], before[2:, 2:])
    assert not f.record_move(11.0, (100.0, 0.0))
    assert u @ f.P[:2, :2] @ u == pytest.approx(4.0 + grow)
    plain = DriftFilter(DriftFilterParams(creep=replace(creep, tau_std=0.0)), x0=np.zeros(4),
                        P0=np.diag([4.0, 4.0, 1e-4, 1e-4]))
    plain.record_move(10.0, (6000.0, 8000.0))
    np.testing.assert_allclose(plain.P, before)


def test_the_creep_history_knows_how_its_creep_depends_on_the_time_constant():
    """``tau_sensitivity`` is ``∂ offset / ∂ ln τ`` of the kept moves (against a finite
    difference of the closed form), frozen moves too."""
    creep = CreepModelParams(amplitude=0.01, tau=0.1, rate_tol=1e-3)
    h = CreepHistory(creep)
    moves = [(10.0, (5000.0, 0.0)), (20.0, (0.0, -3000.0))]
    for t, s in moves:
        h.record(t, s)
    d = 1e-5
    numeric = (creep_offset(25.0, [10.0, 20.0], [m[1] for m in moves], 0.01, 0.1 * math.exp(d))
               - creep_offset(25.0, [10.0, 20.0], [m[1] for m in moves], 0.01, 0.1)) / d
    np.testing.assert_allclose(h.tau_sensitivity(25.0), numeric, rtol=1e-4)
    late = 1e6
    assert h.prune(late) == 2 and len(h) == 0
    np.testing.assert_allclose(h.tau_sensitivity(late),
                               creep_tau_sensitivity(late, [10.0, 20.0], [m[1] for m in moves], 0.01, 0.1),
                               rtol=1e-9)


def test_a_filter_learns_the_creep_time_constant_it_was_wrong_about():
    """Truth creeps with τ 28 % shorter than nominal (and 19 % more): a long travel to one
    of twenty references spread over 15 µm, then three measurements a second apart. With
    ``tau_static`` the filter learns λ = δ ln τ (its error then moves every reference by
    ``c λ / ln 10`` per nm of travel, 1.5 nm a µm here) and predicts the offset after a
    travel better than the same filter treating the time constant's error as noise; it
    resumes from its checkpoint with λ."""
    c_true, tau_true = 0.0119, 0.0715
    creep = CreepModelParams(amplitude=0.01, tau=0.1, amplitude_std=0.003, tau_std=0.2)
    params = DriftFilterParams(q=1e-6, q_offset=0.01, offset_std=1.0, creep=creep)
    v = np.array([0.2, -0.1])
    runs = {}
    for learn in (False, True):
        rng = np.random.default_rng(1)               # the same world for both
        refs = rng.uniform(0.0, 15000.0, (20, 2))
        f = DriftFilter(params, x0=np.zeros(5 if learn else 4), P0=np.diag([4, 4, 1e-4, 1e-4, 0.04][:5 if learn else 4]),
                        statics=int(learn), learn_creep=True, tau_static=0 if learn else None)
        pos, t, moves, errs = np.array([7500.0, 7500.0]), 0.0, [], []
        for k in range(80):
            r = refs[rng.integers(len(refs))]
            t += 1.0
            if np.hypot(*(r - pos)) >= creep.min_step:     # the world creeps as the filter records
                moves.append((t, r - pos))
                f.record_move(t, r - pos)
            pos = r
            for _ in range(3):
                t += 1.0
                truth = v * t + creep_offset(t, [m[0] for m in moves], [m[1] for m in moves], c_true, tau_true)
                if _ == 0:
                    errs.append(np.hypot(*(f.offset(t).offset - truth)))    # predicted after the travel
                f.measure_projected(t, truth + rng.normal(0, 1.0, 2), np.eye(2), np.eye(2))
        runs[learn] = (f, np.sqrt(np.mean(np.square(errs[20:]))))
    f, err = runs[True]
    assert f.tau_static == 0 and abs(f.x[4] - math.log(tau_true / 0.1)) < 0.1
    assert err < 0.25 * runs[False][1]
    back = DriftFilter.from_state(f.params, f.state_dict())
    assert back.tau_static == 0 and np.allclose(back.x, f.x)
    np.testing.assert_allclose(back.creep.tau_sensitivity(t), f.creep.tau_sensitivity(t))
    np.testing.assert_allclose(back.offset(t + 5.0).offset, f.offset(t + 5.0).offset)
    with pytest.raises(ValueError, match="tau_static"):
        DriftFilter(params, x0=np.zeros(4), P0=np.eye(4), tau_static=0)
