"""The creep of moves no longer kept one by one (drift/frozen_creep.py): it goes on
creeping, exactly, in a size that does not grow with the number of moves."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from nanoasm.drift import CreepHistory, CreepModelParams, DriftFilter, DriftFilterParams, creep_offset
from nanoasm.drift.creep import FROZEN_AGE, creep_tau_sensitivity
from nanoasm.drift.frozen_creep import FrozenMoves

TAU = 0.1


def _direct(t: float, times: np.ndarray, steps: np.ndarray) -> np.ndarray:
    return np.log10(1.0 + np.maximum(t - times, 0.0) / TAU) @ steps


def _frozen_as_a_run(times, steps, age: float, every: float, end: float) -> FrozenMoves:
    """Moves frozen as a filter freezes them: every ``every`` s, those older than ``age``."""
    fm, done = FrozenMoves(TAU), 0
    for now in np.arange(0.0, end + 2.0 * every, every):
        j = int(np.searchsorted(times, now - age, side="right"))
        if j > done:
            fm.add(now, times[done:j], steps[done:j])
            done = j
    assert done == len(times)
    return fm


def test_thousands_of_moves_sum_as_if_each_were_kept():
    """5000 moves over 20 000 s (a 1000-object run makes thousands), frozen 30 s old:
    the sum, its rate and its τ weights agree with the direct sum to 1e-11 of Σ|s|,
    in fewer than 100 bins."""
    rng = np.random.default_rng(1)
    times = np.sort(rng.uniform(0.0, 20000.0, 5000))
    steps = rng.normal(0.0, 5000.0, (5000, 2))
    fm = _frozen_as_a_run(times, steps, 30.0, 7.3, 20050.0)
    scale = np.abs(steps).sum()
    assert len(fm) < 100
    for t in (20100.0, 25000.0, 1e6):
        assert np.abs(fm(t) - _direct(t, times, steps)).max() < 1e-11 * scale
        x = (t - times) / TAU
        assert np.abs(fm.tau_weights(t) - (x / (1.0 + x)) @ steps).max() < 1e-11 * scale
        h = 1e-3
        numeric = (_direct(t + h, times, steps) - _direct(t - h, times, steps)) / (2.0 * h)
        assert np.allclose(fm.rate(t), numeric, rtol=1e-6, atol=1e-9 * scale)
    np.testing.assert_allclose(fm.steps, steps.sum(axis=0), rtol=1e-12)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.floats(0.0, 5000.0), st.floats(-2e4, 2e4), st.floats(-2e4, 2e4)),
                min_size=1, max_size=60),
       st.floats(FROZEN_AGE, 400.0), st.floats(0.0, 5000.0))
def test_frozen_sum_is_the_direct_sum(moves, age, later):
    """Any moves, frozen at any age the history freezes them at: the sum at any later time
    agrees with the direct one to 1e-6 of Σ|s| (1e-8 nm a µm at c = 0.01)."""
    moves.sort()
    times = np.array([m[0] for m in moves])
    steps = np.array([m[1:] for m in moves]).reshape(-1, 2)
    end = float(times.max()) + age
    fm = _frozen_as_a_run(times, steps, age, 0.5, end)
    t = end + later
    assert np.abs(fm(t) - _direct(t, times, steps)).max() <= 1e-6 * (np.abs(steps).sum() + 1.0)


def test_state_round_trip_keeps_every_bin():
    rng = np.random.default_rng(2)
    times = np.sort(rng.uniform(0.0, 3000.0, 300))
    steps = rng.normal(0.0, 3000.0, (300, 2))
    fm = _frozen_as_a_run(times, steps, 60.0, 5.0, 3100.0)
    back = FrozenMoves.from_state(TAU, fm.state())
    for t in (3200.0, 9000.0):
        np.testing.assert_array_equal(back(t), fm(t))


def test_a_filter_resumed_from_its_state_goes_on_creeping_as_before():
    """A checkpoint keeps the frozen moves: the resumed filter's creep input equals the
    running one's, later too (a frozen constant stopped creeping at the checkpoint)."""
    params = DriftFilterParams(creep=CreepModelParams(amplitude=0.01, tau=TAU, max_moves=8))
    f = DriftFilter(params)
    rng = np.random.default_rng(3)
    for k in range(60):
        f.record_move(10.0 * (k + 1), rng.normal(0.0, 4000.0, 2))
    assert len(f.creep.old) > 0 and len(f.creep) == 8
    back = DriftFilter.from_state(params, f.state_dict())
    for t in (700.0, 5000.0):
        np.testing.assert_allclose(back.creep.offset(t), f.creep.offset(t), rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(back.creep.tau_sensitivity(t), f.creep.tau_sensitivity(t), rtol=1e-12,
                                   atol=1e-9)


def test_history_offset_is_every_moves_creep_whatever_was_frozen():
    """max_moves 4 of 200 moves: the history's creep input and its τ sensitivity are the
    direct sums over all 200 (the oldest 196 frozen)."""
    p = CreepModelParams(amplitude=0.01, tau=TAU, max_moves=4)
    hist = CreepHistory(p)
    rng = np.random.default_rng(4)
    times = np.cumsum(rng.uniform(1.0, 30.0, 200))
    steps = rng.normal(0.0, 6000.0, (200, 2))
    steps *= np.maximum(1.0, 600.0 / np.hypot(*steps.T))[:, None]     # each longer than min_step
    for t, s in zip(times, steps):
        assert hist.record(float(t), s)
    assert len(hist) == 4
    t = float(times[-1]) + 120.0
    exact = creep_offset(t, times, steps, 0.01, TAU)
    assert np.abs(hist.offset(t) - exact).max() < 1e-9 * 0.01 * np.abs(steps).sum()
    assert np.allclose(hist.tau_sensitivity(t), creep_tau_sensitivity(t, times, steps, 0.01, TAU), rtol=1e-9)
    h = 1e-3
    numeric = (hist.frozen_offset(t + h) - hist.frozen_offset(t - h)) / (2.0 * h)
    assert np.allclose(hist.frozen_rate(t), numeric, rtol=1e-6) and np.abs(numeric).max() > 0.0


def _merged_level_by_level(fm: FrozenMoves, now: float) -> None:
    """:meth:`FrozenMoves._merge` as it was first written, each level's keys listed anew
    from the bins: the order the kept-list merge must add in, to the bit."""
    from nanoasm.drift.frozen_creep import BIN0, BIN_AGE

    level = 0
    while any(key[0] >= level for key in fm.bins):
        w_parent = BIN0 * 2.0 ** (level + 1)
        for key in [key for key in fm.bins if key[0] == level]:
            parent = (level + 1, key[1] // 2)
            if now - (parent[1] + 1) * w_parent >= BIN_AGE * w_parent:
                fm._merge_into(key, parent)
        level += 1


@settings(max_examples=30, deadline=None)
@given(st.lists(st.tuples(st.floats(0.0, 3000.0), st.floats(-2e4, 2e4), st.floats(-2e4, 2e4)),
                min_size=1, max_size=80),
       st.floats(FROZEN_AGE, 300.0), st.floats(0.1, 40.0))
def test_merging_keeps_the_bins_and_their_order_to_the_bit(moves, age, every):
    """The merge that keeps each level's keys as it goes gives the bins, their moments to
    the bit and their order, that listing each level anew gave."""
    moves.sort()
    times = np.array([m[0] for m in moves])
    steps = np.array([m[1:] for m in moves]).reshape(-1, 2)
    fast, slow, done = FrozenMoves(TAU), FrozenMoves(TAU), 0
    slow._merge = lambda now: _merged_level_by_level(slow, now)
    for now in np.arange(0.0, float(times.max()) + age + 2.0 * every, every):
        j = int(np.searchsorted(times, now - age, side="right"))
        for fm in (fast, slow):
            fm.add(now, times[done:j], steps[done:j])
        done = j
        assert list(fast.bins) == list(slow.bins)
        for key in fast.bins:
            assert np.array_equal(fast.bins[key], slow.bins[key])
