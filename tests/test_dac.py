"""Path to DAC: frames, motion limits, range validation, streaming memory, quantisation."""

from __future__ import annotations

import math
import tracemalloc

import numpy as np
import pytest
from hypothesis import event, given
from hypothesis import strategies as st

from nanoasm.errors import InstrumentLimitError
from nanoasm.executor.dac import plan_dac
from nanoasm.executor.dac_frames import (LinearDrift, PushLoad, compensate, deflection_offset,
                                         quantisation_error, uncompensate)
from nanoasm.executor.trajectory import LIFT, LOWER, PUSH, TRAVEL, Move, operation
from nanoasm.instrument import InstrumentConfig, check_samples
from nanoasm.world.cantilever import SEED_LEVER, Cantilever

CFG = InstrumentConfig()
REST = CFG.rest_codes()
C = deflection_offset(PushLoad.from_preload(CFG), CFG.scan_angle)  # R⁻¹δ at the preload, nm
RTOL = 1e-9


def stream(plan, size=4096):
    """Concatenated chunks, each re-checked against the sample before it."""
    previous, parts = plan.current, []
    for chunk in plan.chunks(size):
        assert 1 <= len(chunk) <= size
        check_samples(chunk.codes, plan.config, previous)
        previous = chunk.codes[-1]
        parts.append(chunk)
    cat = {name: np.concatenate([getattr(c, name) for c in parts]) for name in ("codes", "t", "nm", "kind")}
    return cat


def assert_within_limits(out, cfg=CFG, start_codes=REST):
    """Speed and acceleration from the exact commands and from the rounded codes."""
    dt = 1.0 / cfg.sample_rate
    nm = np.vstack([cfg.codes_to_nm(start_codes)[None], out["nm"]])
    for pos, slack_v, slack_a in (
            (nm, 0.0, 0.0),
            (cfg.codes_to_nm(np.vstack([start_codes, out["codes"]])),
             math.hypot(*cfg.nm_per_code[:2]), 2 * math.hypot(*cfg.nm_per_code[:2]))):
        step = np.diff(pos, axis=0)
        assert np.hypot(step[:, 0], step[:, 1]).max() <= cfg.max_step * (1 + RTOL) + slack_v
        assert np.abs(step[:, 2]).max() <= cfg.max_step * (1 + RTOL) + cfg.nm_per_code[2]
        acc = np.diff(pos, 2, axis=0)
        assert np.hypot(acc[:, 0], acc[:, 1]).max() <= cfg.max_accel * dt * dt * (1 + RTOL) + slack_a
        assert np.abs(acc[:, 2]).max() <= cfg.max_accel * dt * dt * (1 + RTOL) + 2 * cfg.nm_per_code[2]


def runs(kind):
    """(kind, first, last) for each run of equal kinds."""
    edges = np.flatnonzero(np.diff(kind)) + 1
    starts = np.concatenate([[0], edges])
    stops = np.concatenate([edges, [len(kind)]]) - 1
    return [(int(kind[a]), int(a), int(b)) for a, b in zip(starts, stops)]


def within_a_code(codes, expected_nm, cfg=CFG):
    return np.all(np.abs(cfg.codes_to_nm(codes) - expected_nm) <= cfg.nm_per_code + 1e-9)


# -- frames: rotation R(ψ) and deflection compensation ------------------------------------------

def r_eq_3_7(psi):
    c, s = math.cos(math.radians(psi)), math.sin(math.radians(psi))
    return np.array([[-c, s], [-s, -c]])


@given(st.floats(-360, 360), st.floats(-10, 10), st.floats(-10, 10))
def test_deflection_offset_rotates_back_to_the_lever_frame(psi, sn, sl):
    off = deflection_offset(PushLoad(sn, sl), psi)
    delta = np.array([SEED_LEVER.c2 * sn, SEED_LEVER.c1 * sl])  # eq. 3.30-3.34, cantilever frame
    np.testing.assert_allclose(r_eq_3_7(psi) @ off, delta, atol=1e-9)
    assert math.hypot(*off) == pytest.approx(math.hypot(*delta), abs=1e-9)


def test_deflection_offset_closed_forms():
    sn, sl = 2.0, 3.0
    dx, dy = 23.0 * sn, SEED_LEVER.c1 * sl
    np.testing.assert_allclose(deflection_offset(PushLoad(sn, sl), 0.0), [-dx, -dy], atol=1e-12)
    np.testing.assert_allclose(deflection_offset(PushLoad(sn, sl), 180.0), [dx, dy], atol=1e-12)
    np.testing.assert_allclose(deflection_offset(PushLoad(sn, sl), 90.0), [-dy, dx], atol=1e-12)
    # the preload's deflection at ψ = 0: the tip leads along -x by C2 preload / K_n
    np.testing.assert_allclose(C, [-23.0 * 100.0 / 89.0, 0.0], atol=1e-12)


@given(st.lists(st.tuples(st.floats(-1e5, 1e5), st.floats(-1e5, 1e5)), min_size=1, max_size=8),
       st.floats(-360, 360), st.floats(-10, 10), st.floats(-10, 10), st.floats(0, 1))
def test_compensation_puts_the_deflected_tip_on_target(targets, psi, sn, sl, f):
    targets = np.array(targets)
    off = deflection_offset(PushLoad(sn, sl), psi)
    frac = np.full(len(targets), f)
    cmd = compensate(targets, frac, off)
    np.testing.assert_allclose(uncompensate(cmd, frac, off), targets, atol=1e-8)
    # the piezo sits opposite the rotated deflection: target - f R⁻¹δ
    delta = np.array([SEED_LEVER.c2 * sn, SEED_LEVER.c1 * sl])
    np.testing.assert_allclose(cmd, targets - f * (r_eq_3_7(psi).T @ delta), atol=1e-8)


def test_saturated_signals_are_refused():
    with pytest.raises(ValueError, match="sn_bar"):
        deflection_offset(PushLoad(12.0), 0.0)
    with pytest.raises(ValueError, match="sl_bar"):
        PushLoad(1.0, math.nan)


def test_push_samples_put_the_tip_on_the_layout_path_plus_drift():
    push = [[20000.0, 30000.0], [21000.0, 30500.0], [21500.0, 32000.0]]
    drift = (120.0, -80.0)
    cfg = InstrumentConfig(scan_angle=37.0)
    load = PushLoad(1.5, 0.4)
    plan = plan_dac(operation(push), cfg, REST, drift=drift, load=load)
    out = stream(plan)
    off = deflection_offset(load, 37.0)
    tip = out["nm"][out["kind"] == PUSH][:, :2] + off - drift
    # every push sample's tip lies on the layout polyline
    a, b = np.array(push[:-1]), np.array(push[1:])
    d = b - a
    u = np.clip(np.einsum("nsk,sk->ns", tip[:, None] - a, d) / (d * d).sum(1), 0, 1)
    dist = np.linalg.norm(tip[:, None] - (a + u[..., None] * d), axis=2).min(axis=1)
    assert dist.max() < 1e-6
    assert np.all(out["nm"][out["kind"] == PUSH][:, 2] == -cfg.preload)


# -- random polylines: limits, range, endpoints -------------------------------------------------

EDGES = [0.0, 25.0, 26.0, 45000.0, 89974.0, 89975.0, 90000.0]
coord = st.one_of(st.floats(-3000, 93000), st.sampled_from(EDGES))
point = st.tuples(coord, coord)


@st.composite
def polyline(draw):
    pts = draw(st.lists(point, min_size=1, max_size=4))
    if draw(st.booleans()):  # repeats and sub-nm segments
        i = draw(st.integers(0, len(pts) - 1))
        tiny = draw(st.sampled_from([0.0, 1e-9, 1e-3, 0.5]))
        pts.insert(i + 1, (pts[i][0] + tiny, pts[i][1]))
    return pts


def expected_vertices(ops, drift):
    """Every commanded position of the operations, in the order :func:`operation` visits
    them, computed as the plan does: (p - f c) + d."""
    out = []
    for travel, push in ops:
        for p in travel:
            out.append(np.asarray(p, float) + drift)
        start, end = np.asarray(push[0], float), np.asarray(push[-1], float)
        out += [start + drift]
        out += [(np.asarray(p, float) - C) + drift for p in push]
        out += [end + drift]
    return np.array(out)


@given(st.lists(st.tuples(st.lists(point, max_size=2), polyline()), min_size=1, max_size=2),
       st.one_of(st.just((0.0, 0.0)), st.tuples(st.floats(-400, 400), st.floats(-400, 400))))
def test_random_polylines_stream_within_limits_or_are_refused_up_front(ops, drift):
    moves = [m for travel, push in ops for m in operation(push, travel)]
    cmds = expected_vertices(ops, np.array(drift))
    in_range = bool(np.all((cmds >= 0) & (cmds <= 90000.0)))
    event("streamed" if in_range else "refused")
    if not in_range:
        with pytest.raises(InstrumentLimitError, match=r"moves\[\d+\] \((push|travel)\) point \d+"):
            plan_dac(moves, CFG, REST, drift=drift)
        return
    plan = plan_dac(moves, CFG, REST, drift=drift)
    out = stream(plan)
    assert len(out["codes"]) == plan.n_samples
    assert_within_limits(out)
    # z levels, and each operation's ends within one DAC code
    seen = runs(out["kind"])
    lowers = [r for r in seen if r[0] == LOWER]
    assert len(lowers) >= 1
    for (kind, a, b) in seen:
        z = out["nm"][a:b + 1, 2]
        if kind == PUSH:
            assert np.all(z == -CFG.preload)
        if kind == TRAVEL and a > 0:
            assert np.all(z == CFG.lift)
    last_push = ops[-1][1]
    end = np.append(np.asarray(last_push[-1], float) + drift, CFG.lift)
    assert within_a_code(out["codes"][-1], end)
    pushes_end = out["codes"][[b for kind, a, b in seen if kind == LOWER][-1]]
    assert within_a_code(pushes_end, np.append(np.asarray(last_push[0], float) - C + drift, -CFG.preload))
    after_lower = seen[seen.index(lowers[-1]) + 1]
    if after_lower[0] == PUSH:
        assert within_a_code(out["codes"][after_lower[2]],
                             np.append(np.asarray(last_push[-1], float) - C + drift, -CFG.preload))


@given(st.floats(1e-12, 1.0))
def test_tiny_segments_take_a_sample_each_within_limits(step):
    push = [[40000.0, 40000.0], [40000.0 + step, 40000.0], [40000.0 + step, 40000.0 + step]]
    plan = plan_dac(operation(push), CFG, REST)
    out = stream(plan)
    assert_within_limits(out)
    assert within_a_code(out["codes"][-1], [40000.0 + step, 40000.0 + step, CFG.lift])


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_nan_and_inf_points_are_refused_before_any_sample(bad):
    with pytest.raises(ValueError, match=r"points\[1\] = \(.*, 2000.0\) is not finite"):
        operation([[1000.0, 1000.0], [bad, 2000.0]])
    with pytest.raises(ValueError, match=r"moves\[1\]: points\[1\]"):
        plan_dac([("travel", [[0.0, 0.0]]), ("push", [[1000.0, 1000.0], [bad, 2000.0]])], CFG, REST)
    with pytest.raises(ValueError, match="points"):
        Move("travel", [[bad, 0.0]])
    with pytest.raises(ValueError, match="drift"):
        plan_dac(operation([[1000.0, 1000.0]]), CFG, REST, drift=(bad, 0.0))
    with pytest.raises(ValueError, match="t0"):
        plan_dac(operation([[1000.0, 1000.0]]), CFG, REST, t0=bad)
    with pytest.raises(InstrumentLimitError, match="drift is not finite"):
        plan_dac(operation([[1000.0, 1000.0]]), CFG, REST, drift=lambda t: np.full((len(t), 2), bad))
    with pytest.raises(InstrumentLimitError):
        plan_dac(operation([[1000.0, 1000.0]]), CFG, np.array([1.0, bad, 3.0]))


@pytest.mark.parametrize("huge", [1e12, 1e300, 1.7e308, -1.7e308])
def test_huge_points_are_refused_naming_the_point(huge):
    with pytest.raises(InstrumentLimitError, match=r"moves\[1\] \(push\) point 2"):
        plan_dac(operation([[1000.0, 1000.0], [2000.0, 1000.0], [huge, 1000.0]]), CFG, REST)


def test_out_of_range_after_compensation_names_the_point_and_sends_nothing():
    # 89980 is in range, but the compensated command at ψ = 0 sits 25.8 nm further out
    moves = operation([[80000.0, 500.0], [89980.0, 500.0]])
    with pytest.raises(InstrumentLimitError, match=r"moves\[1\] \(push\) point 1 .* x = 90005\.8"):
        plan_dac(moves, CFG, REST)
    # lifted, the same point needs no compensation; with drift it leaves the range again
    assert plan_dac([("travel", [[89980.0, 500.0]])], CFG, REST).n_samples > 0
    with pytest.raises(InstrumentLimitError, match=r"moves\[0\] \(travel\) point 0 .*drift \(\+30\.0"):
        plan_dac([("travel", [[89980.0, 500.0]])], CFG, REST, drift=(30.0, 0.0))


def test_linear_drift_is_validated_at_the_time_each_point_is_reached():
    moves = [("travel", [[89000.0, 45000.0], [45000.0, 45000.0]])]
    # 2 µm/s of drift moves the first point out of range only if it is reached late
    assert plan_dac(moves, CFG, REST, drift=LinearDrift((900.0, 0.0), (2.0, 0.0))).n_samples
    with pytest.raises(InstrumentLimitError, match=r"moves\[0\] \(travel\) point 0"):
        plan_dac(moves, CFG, REST, t0=100.0, drift=LinearDrift((900.0, 0.0), (2.0, 0.0)))


def test_time_varying_drift_is_followed_per_sample():
    def drift(t):
        t = np.asarray(t, float)
        return np.column_stack([50.0 * np.sin(0.5 * t), 20.0 * t])

    moves = operation([[30000.0, 30000.0], [33000.0, 31000.0]])
    plan = plan_dac(moves, CFG, REST, t0=3.0, drift=drift)
    out = stream(plan)
    assert_within_limits(out)
    np.testing.assert_allclose(out["t"], 3.0 + np.arange(1, plan.n_samples + 1) / CFG.sample_rate)
    d_end = drift(out["t"][-1:])[0]
    assert within_a_code(out["codes"][-1], [33000.0 + d_end[0], 31000.0 + d_end[1], CFG.lift])


def test_a_drift_faster_than_the_scanner_is_refused():
    with pytest.raises(InstrumentLimitError, match="drift of"):
        plan_dac(operation([[30000.0, 30000.0]]), CFG, REST,
                 drift=LinearDrift(velocity=(0.6 * CFG.max_speed, 0.0)))


def test_a_drift_that_jumps_between_validated_times_is_stopped_by_the_chunk_check():
    def jumpy(t):
        t = np.asarray(t, float)
        jump = (np.abs(t - 0.25) < 1e-7) * 5000.0  # at sample 250, between validated times
        return np.column_stack([jump, np.zeros_like(t)])

    plan = plan_dac([("travel", [[30000.0, 30000.0]])], CFG, REST, drift=jumpy)
    sent, previous = [], plan.current
    with pytest.raises(InstrumentLimitError, match="chunk from sample"):
        for chunk in plan.chunks(64):
            check_samples(chunk.codes, CFG, previous)
            previous = chunk.codes[-1]
            sent.append(chunk)
    assert sent and sent[-1].t[-1] < 0.25


# -- moves, speed caps, start -------------------------------------------------------------------

def test_push_speed_cap_and_move_validation():
    plan = plan_dac(operation([[10000.0, 10000.0], [14000.0, 10000.0]], push_speed=2000.0), CFG, REST)
    out = stream(plan)
    push = out["nm"][out["kind"] == PUSH]
    assert np.abs(np.diff(push[:, 0])).max() <= 2000.0 / CFG.sample_rate * (1 + RTOL)
    assert np.abs(np.diff(push[:, 0])).max() > 0.9 * 2000.0 / CFG.sample_rate
    with pytest.raises(ValueError, match="travel, push"):
        Move("hover", [[0.0, 0.0]])
    with pytest.raises(ValueError, match="speed"):
        Move("push", [[0.0, 0.0]], speed=-1.0)
    with pytest.raises(ValueError, match=r"\(K, 2\)"):
        Move("push", [[0.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="at least one move"):
        plan_dac([], CFG, REST)


def test_consecutive_pushes_stay_in_contact_and_the_path_ends_lifted():
    moves = [("travel", [[10000.0, 10000.0]]), ("push", [[10000.0, 10000.0], [11000.0, 10000.0]]),
             ("push", [[11000.0, 10000.0], [11000.0, 11000.0]]), ("push", [[15000.0, 15000.0]])]
    out = stream(plan_dac(moves, CFG, REST))
    kinds = [k for k, _, _ in runs(out["kind"])]
    assert kinds == [TRAVEL, LOWER, PUSH, LIFT, TRAVEL, LOWER, LIFT]
    assert out["nm"][-1, 2] == CFG.lift


def test_start_is_the_instruments_current_sample():
    low = CFG.nm_to_codes(np.array([5000.0, 6000.0, -80.0]))  # in contact, far from rest
    plan = plan_dac(operation([[5200.0, 6000.0]]), CFG, low)
    out = stream(plan)
    assert_within_limits(out, start_codes=low)
    assert out["kind"][0] == TRAVEL and out["nm"][0, 2] > -80.0  # it rises first, in place
    np.testing.assert_allclose(out["nm"][0, :2], CFG.codes_to_nm(low)[:2], atol=1e-9)
    with pytest.raises(ValueError, match="current"):
        plan_dac(operation([[5200.0, 6000.0]]), CFG, low[:2])
    with pytest.raises(InstrumentLimitError, match="outside the DAC range"):
        plan_dac(operation([[5200.0, 6000.0]]), CFG, np.array([70000, 0, 0]))


def test_chunking_does_not_change_the_samples():
    plan = plan_dac(operation([[10000.0, 10000.0], [10500.0, 10200.0]]), CFG, REST, drift=(3.0, 4.0))
    a, b = stream(plan, 1), stream(plan, 4096)
    np.testing.assert_array_equal(a["codes"], b["codes"])
    with pytest.raises(ValueError, match="size"):
        plan.chunks(0)


# -- memory and quantisation --------------------------------------------------------------------

def test_a_one_metre_zigzag_streams_in_bounded_memory():
    cfg = InstrumentConfig(max_speed=1.0e6, max_accel=1.0e9)  # 1 µm per sample: a 1 m path, 1M samples
    legs = 12500
    x = np.where(np.arange(legs + 1) % 2 == 0, 5000.0, 85000.0)
    y = np.linspace(5000.0, 85000.0, legs + 1)
    plan = plan_dac([("travel", np.column_stack([x, y]))], cfg, cfg.rest_codes())
    size = 4096
    assert plan.n_samples > 200 * size
    chunk_bytes = size * (3 + 1 + 3) * 8 + size  # codes, t, nm, kind
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        n, previous = 0, plan.current
        for chunk in plan.chunks(size):
            n += len(chunk)
            previous = chunk.codes[-1]
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    assert n == plan.n_samples
    assert within_a_code(previous, [x[-1], y[-1], cfg.lift], cfg)
    assert peak < 8 * chunk_bytes, f"peak {peak / 1e6:.2f} MB for {n} samples"


def test_quantisation_error_is_half_a_code_and_met():
    q = quantisation_error(CFG)
    assert q[0] == pytest.approx(math.hypot(90000 / 65535, 90000 / 65535) / 2)  # 0.971 nm
    assert q[1] == pytest.approx(5000 / 65535 / 2)
    out = stream(plan_dac(operation([[12345.678, 23456.789], [13001.3, 23999.9]]), CFG, REST, drift=(0.3, 0.7)))
    err = np.abs(CFG.codes_to_nm(out["codes"]) - out["nm"])
    assert np.all(err <= CFG.nm_per_code / 2 + 1e-9)
    assert np.hypot(err[:, 0], err[:, 1]).max() <= q[0] + 1e-9


def test_a_tolerance_finer_than_the_dac_is_refused():
    coarse = InstrumentConfig(dac_bits=8)  # 353 nm per code
    assert plan_dac(operation([[1000.0, 1000.0]]), CFG, REST, tolerance=50.0).n_samples
    with pytest.raises(InstrumentLimitError, match="more than the tolerance 50 nm"):
        plan_dac(operation([[1000.0, 1000.0]]), coarse, coarse.rest_codes(), tolerance=50.0)
    with pytest.raises(InstrumentLimitError, match="tolerance 0.5 nm"):
        plan_dac(operation([[1000.0, 1000.0]]), CFG, REST, tolerance=0.5)
    with pytest.raises(ValueError, match="tolerance"):
        plan_dac(operation([[1000.0, 1000.0]]), CFG, REST, tolerance=-1.0)


def test_coarse_dac_streams_within_slew_with_rounding():
    cfg = InstrumentConfig(dac_bits=10, sample_rate=20000.0)  # 88 nm per code, 2.5 nm per sample
    plan = plan_dac(operation([[10000.0, 20000.0], [12000.0, 20500.0]]), cfg, cfg.rest_codes())
    out = stream(plan)
    assert_within_limits(out, cfg, cfg.rest_codes())
    assert within_a_code(out["codes"][-1], [12000.0, 20500.0, cfg.lift], cfg)


def test_other_levers_and_angles_move_the_push_command():
    lever = Cantilever(c2=40.0)
    cfg = InstrumentConfig(scan_angle=180.0)
    out = stream(plan_dac(operation([[30000.0, 30000.0], [31000.0, 30000.0]]), cfg, REST, lever=lever))
    push = out["nm"][out["kind"] == PUSH]
    # ψ = 180°: R = I, the command trails the target by C2 S̄n along +x of the lever = +x
    np.testing.assert_allclose(push[-1, :2], [31000.0 - 40.0 * 100.0 / 89.0, 30000.0], atol=1e-9)


def test_a_sweep_that_leaves_the_range_between_in_range_vertices_is_refused():
    # A fast drift against the motion: the tip lands on x = 89990 nm at its own time, but
    # just before, while decelerating, the drift has not yet pulled it back (~v²/2a = 200 nm).
    moves = [("travel", [[89990.0, 45000.0]])]
    velocity = (-20000.0, 0.0)
    early = plan_dac(moves, CFG, REST, drift=LinearDrift(velocity=velocity))  # in range throughout
    t_end = early.duration
    with pytest.raises(InstrumentLimitError, match=r"moves\[0\] \(travel\) point 0"):
        plan_dac(moves, CFG, REST, drift=LinearDrift(velocity=velocity, t_ref=t_end))
    # the same timing, drift shifted by a constant so that it is zero on arrival
    x = stream(early)["nm"][:, 0] - velocity[0] * t_end
    assert x[-1] == pytest.approx(89990.0)
    assert x.max() > 90000.0 + 100.0


@pytest.mark.parametrize("size", [1, 7, 100, 4095, 4096, 5000])
def test_chunks_cut_from_blocks_are_the_chunks_rendered_alone(size):
    """:meth:`DacPlan.chunks` renders blocks of whole chunks at once; every chunk is, to the
    bit, the one rendered and checked alone (`render` of its samples), with a drift that
    creeps after moves recorded and still to come (a matrix product's rows would differ
    with the block's size), and a jump that fails a block streams the chunks before it."""
    from nanoasm.drift.creep import CreepHistory, CreepingOffset, CreepModelParams

    hist = CreepHistory(CreepModelParams(amplitude=0.01, tau=0.1, min_step=100.0))
    rng = np.random.default_rng(size)
    for t in np.sort(rng.uniform(0.0, 100.0, 40)):
        hist.record(float(t), rng.normal(0.0, 800.0, 2))
    creeping = CreepingOffset((3.0, -2.0), (0.3, -0.2), 101.0, hist, pending=[(101.4, (900.0, -300.0))])
    moves = [("travel", [[12000.0, 9000.0]]), ("push", [[12000.0, 9000.0], [12900.0, 9400.0]])]
    plan = plan_dac(moves, CFG, REST, t0=101.0, drift=creeping)
    got = list(plan.chunks(size))
    assert sum(len(c) for c in got) == plan.n_samples
    for c in got:
        alone = plan.render(np.arange(c.first, c.first + len(c)))
        for name in ("codes", "t", "nm", "kind"):
            np.testing.assert_array_equal(getattr(c, name), getattr(alone, name))

    def jumpy(t):
        t = np.asarray(t, float)
        return creeping(t) + np.column_stack([(np.abs(t - 101.25) < 1e-7) * 5000.0, np.zeros_like(t)])

    plan = plan_dac(moves, CFG, REST, t0=101.0, drift=jumpy)
    sent = []
    with pytest.raises(InstrumentLimitError, match="chunk from sample"):
        for chunk in plan.chunks(size):
            sent.append(chunk)
    assert sum(len(c) for c in sent) == size * (249 // size)      # sample 250 jumps: its chunk fails
