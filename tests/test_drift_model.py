"""The true drift: deterministic per seed, independent of chunking, right statistics, creep."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from nanoasm.world.params import CreepParams, DriftParams
from nanoasm.world.sim import DriftModel

DRIFT = DriftParams()
CREEP = CreepParams()


def model(seed: int, drift: DriftParams = DRIFT, creep: CreepParams = CREEP, **kw) -> DriftModel:
    return DriftModel(drift, creep, np.random.default_rng(seed), **kw)


# -- determinism -----------------------------------------------------------------------------------

def test_same_seed_same_drift_other_seed_other_drift():
    t = np.linspace(0, 7200, 301)
    a, b, c = model(3).offset(t), model(3).offset(t), model(4).offset(t)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


@given(st.lists(st.integers(1, 2999), max_size=8, unique=True), st.randoms(use_true_random=False))
def test_chunking_and_query_order_do_not_matter(cuts, rnd):
    t = np.sort(np.random.default_rng(0).uniform(0, 30000, 3000))  # spans several noise blocks
    whole = np.array(model(11).thermal(t))
    bounds = [0, *sorted(cuts), len(t)]
    chunks = list(itertools.pairwise(bounds))
    rnd.shuffle(chunks)
    m = model(11)
    parts = np.empty_like(whole)
    for a, b in chunks:
        parts[:, a:b] = m.thermal(t[a:b])
    np.testing.assert_array_equal(parts, whole)
    assert m.thermal(float(t[7])) == (whole[0, 7], whole[1, 7])


def test_large_epoch_loses_no_precision():
    early, late = model(5), model(5, epoch=1.0e9)
    for tau in (0.0, 0.37, 123.4, 5000.5):
        np.testing.assert_allclose(late.thermal(1.0e9 + tau), early.thermal(tau), atol=1e-5)
    assert late.thermal(1.0e9) == (0.0, 0.0)
    with pytest.raises(ValueError, match="precede the epoch"):
        late.thermal(0.0)
    assert late.thermal(1.0e9 - 1e-7) == (0.0, 0.0)     # the epoch, rounded below it


# -- statistics -------------------------------------------------------------------------------------

def test_steady_velocity_alone_is_exact():
    m = model(1, DriftParams(velocity=(0.08, -0.05), random_walk=0.0))
    t = np.array([0.0, 1.5, 1000.0, 36000.0])
    dx, dy = m.thermal(t)
    np.testing.assert_allclose(dx, 0.08 * t, rtol=1e-12)
    np.testing.assert_allclose(dy, -0.05 * t, rtol=1e-12)


def test_random_walk_variance_matches_the_closed_form():
    q = 0.3
    params = DriftParams(velocity=(0.0, 0.0), random_walk=q)
    times = np.array([2.0, 5.0, 20.0, 300.0, 2000.0])  # a few grid steps: the exact discretisation
    xs = []
    for seed in range(1500):
        m = model(seed, params)
        xs.append(np.stack(m.thermal(times)))
    xs = np.array(xs)  # (seed, axis, time)
    var_x = xs.reshape(-1, len(times)).var(axis=0)
    # 3000 samples: the variance estimate has a relative sd of 2.6 %
    np.testing.assert_allclose(var_x / (q**2 * times), 1.0, atol=0.12)
    assert abs(xs.mean()) < 0.1 * math.sqrt(q**2 * times[-1])


def test_long_runs_reach_hundreds_of_nm_at_the_defaults():
    hours = np.array([1.0, 3.0]) * 3600
    mags = np.array([np.hypot(*model(s).offset(hours)) for s in range(20)])  # (seed, time)
    median_1h, median_3h = np.median(mags, axis=0)
    assert 150 < median_1h < 1000 and 400 < median_3h < 3000


@pytest.mark.parametrize("grid", [1.0, 2.5])
def test_drift_is_smooth_and_velocity_is_its_derivative(grid):
    m = model(9, DriftParams(velocity=(0.02, 0.01), random_walk=0.01), grid=grid)
    t = np.array([3.0, 3.5, 1000.25, 4096.0, 4097.75]) * grid  # nodes, mid-steps, a block edge
    h = 1e-4
    fd = (np.array(m.thermal(t + h)) - np.array(m.thermal(t - h))) / (2 * h)
    # at nodes the curvature jumps (C1 Hermite): the central difference errs by ~h * jump
    np.testing.assert_allclose(np.array(m.velocity(t)), fd, rtol=1e-5, atol=1e-5)


# -- creep ----------------------------------------------------------------------------------------------

def still(seed: int = 0, **creep) -> DriftModel:
    return model(seed, DriftParams(velocity=(0.0, 0.0), random_walk=0.0), CreepParams(**creep))


def test_creep_is_logarithmic_in_time_after_a_step():
    m = still(amplitude=0.02, tau=0.1)
    t0 = 50.0
    assert m.record_move(t0, 3000.0, -4000.0)
    for decades in (1, 2, 3, 4):
        cx, cy = m.creep(t0 + 0.1 * (10**decades - 1))
        assert (cx, cy) == pytest.approx((0.02 * 3000 * decades, -0.02 * 4000 * decades))
    assert m.creep([0.0, t0]) == (pytest.approx([0, 0]), pytest.approx([0, 0]))


def test_creep_grows_monotonically_along_the_step():
    m = still()
    m.record_move(10.0, 2000.0, 0.0)
    t = np.linspace(0, 5000, 2001)
    cx, cy = m.creep(t)
    assert np.all(np.diff(cx) >= 0) and cx[-1] > 0 and np.all(cy == 0)
    # the sample appears to move back: the offset has the opposite sign
    ox, _ = m.offset(t)
    np.testing.assert_allclose(ox, -cx)


def test_small_moves_add_no_creep():
    m = still(min_step=500.0)
    assert not m.record_move(1.0, 300.0, 300.0)
    assert m.creep(100.0) == (0.0, 0.0)


def test_a_move_and_its_return_creep_away():
    m = still()
    m.record_move(0.0, 5000.0, 0.0)
    m.record_move(30.0, -5000.0, 0.0)
    t = np.array([30.0, 100.0, 1000.0, 10000.0])
    cx, _ = m.creep(t)
    assert np.all(np.diff(cx) < 0) and cx[-1] < 0.05 * cx[0]


def test_a_motion_creeps_as_it_goes_in_pieces():
    """A streamed motion is recorded in pieces as it goes: at every ``min_step`` of
    displacement from where the last recorded move ended, at least ``MIN_PIECE_TIME``
    after it, each at its own sample. A push of seconds (or legs in a row without a rest)
    creeps during itself, not from its end. What is left when XY stops ends a move there,
    ``stop_samples`` after, if it is ``min_step`` long (else it is carried on)."""
    from nanoasm.drift.creep import MIN_PIECE_TIME
    from nanoasm.world.sim.stream import MoveTracker

    m = still(min_step=100.0)
    tracker = MoveTracker(m, np.zeros(2), stop_samples=50)
    n, rate = 200, 1000.0                              # 10 m/s: 100 nm in 10 ms
    nm = np.column_stack([np.linspace(10.0, 2000.0, n), np.zeros(n), np.zeros(n)])
    codes = np.round(nm * 10).astype(np.int64)
    t = 1.0 + np.arange(1, n + 1) / rate
    tracker.track(nm, codes, np.zeros(3, np.int64), t)
    assert MIN_PIECE_TIME == 0.05
    assert m._moves_t == pytest.approx([1.010, 1.060, 1.110, 1.160])   # at 100 nm, then 50 ms apart
    np.testing.assert_allclose(m._moves_s, [(100.0, 0.0), (500.0, 0.0), (500.0, 0.0), (500.0, 0.0)])
    more = np.column_stack([np.linspace(2010.0, 2550.0, 55), np.zeros(55), np.zeros(55)])
    t_more = t[-1] + np.arange(1, 56) / rate
    tracker.track(more, np.round(more * 10).astype(np.int64), codes[-1], t_more)
    assert m._moves_t[-1] == pytest.approx(1.210) and m._moves_s[-1] == pytest.approx((500.0, 0.0))
    assert m.creep(t_more[-1])[0] > m.creep(t[-1])[0] > 0.0        # crept while it went on
    tracker.jump(t_more[-1] + 2.0, np.array([2550.0, 600.0]))      # a pause, then a scan line elsewhere
    assert m._moves_t[-2:] == pytest.approx([t_more[-1] + 50 / rate, t_more[-1] + 2.0])
    np.testing.assert_allclose(m._moves_s[-2:], [(450.0, 0.0), (0.0, 600.0)])   # ended where XY stopped


def test_creep_moves_of_a_slow_push_every_min_step_and_where_it_rests():
    """At a push's speed the pieces are ``min_step`` apart; none before ``MIN_PIECE_TIME``
    after the last recorded move; a path that never gets ``min_step`` away has none; a
    rest ends a move if it is ``min_step`` from the last one."""
    from nanoasm.drift.creep import creep_moves

    t = np.arange(1, 20001) / 1000.0                 # 20 s at 200 nm/s: 4 µm
    xy = np.column_stack([200.0 * t, np.zeros_like(t)])
    ks = creep_moves((0.0, 0.0), xy, t, 500.0)
    np.testing.assert_allclose(xy[ks, 0], [500.0, 1000.0, 1500.0, 2000.0, 2500.0, 3000.0, 3500.0, 4000.0])
    assert creep_moves((0.0, 0.0), xy, t, 500.0, last=10.0)[0] == np.searchsorted(t, 10.05)
    back = np.column_stack([400.0 * np.sin(t), np.zeros_like(t)])
    assert creep_moves((0.0, 0.0), back, t, 500.0).size == 0
    # a fast travel (20 µm/s) is cut every MIN_PIECE_TIME; XY at rest 700 nm after the
    # first piece ends a move there (sample 60), 100 nm after a piece does not (sample 120)
    fast = np.column_stack([20.0 * np.arange(1, 201), np.zeros(200)])
    ks = creep_moves((0.0, 0.0), fast, np.arange(1, 201) / 1000.0, 500.0, rests=[59, 119])
    np.testing.assert_allclose(fast[ks, 0], [500.0, 1200.0, 2200.0, 3200.0])


def test_bad_queries_are_refused():
    m = model(0)
    with pytest.raises(ValueError, match="finite"):
        m.thermal(np.nan)
    with pytest.raises(ValueError, match="finite"):
        m.record_move(1.0, math.inf, 0.0)
    with pytest.raises(ValueError, match="grid"):
        model(0, grid=0.0)


def test_short_moves_carry_their_displacement_into_the_next_move():
    """The simulator's move tracker: a move under min_step is not recorded and does not
    restart the chain, so every displacement creeps (creep is linear in the step)."""
    from nanoasm.world.params import CreepParams, DriftParams
    from nanoasm.world.sim.stream import MoveTracker

    m = DriftModel(DriftParams(velocity=(0.0, 0.0), random_walk=0.0),
                   CreepParams(amplitude=0.01, tau=0.1, min_step=500.0), np.random.default_rng(0))
    tracker = MoveTracker(m, np.zeros(2), stop_samples=1)
    tracker.jump(1.0, np.array([300.0, 0.0]))       # too short: carried
    tracker.jump(2.0, np.array([300.0, 400.0]))     # 500 from the chain's start: recorded
    tracker.jump(3.0, np.array([900.0, 400.0]))     # 600 from there: recorded
    assert m._moves_t == [2.0, 3.0]
    assert np.allclose(m._moves_s, [(300.0, 400.0), (600.0, 0.0)])
