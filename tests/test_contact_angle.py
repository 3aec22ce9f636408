"""Where a pushed particle sits on the tip, from the signals of the push (issue 13, in-push
tracking's measurement), against the simulated world's own physics."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from simkit import particle, push, world

from nanoasm.executor.contact_angle import MIN_FORCE, PushSignals, contact_angle
from nanoasm.executor.monitor import PushMonitor
from nanoasm.world.cantilever import SEED_LEVER

R, TIP, LEAD = 45.0, 10.0, 20.0


def _measured(direction, offset: float):
    """A 90 nm particle pushed 400 nm along ``direction`` with the tip's line ``offset`` nm
    to the left of its centre, put down LEAD nm short of contact: α as the push's kept
    signals (:class:`PushSignals`, as a streamed push keeps them) give it at the end, and
    as the simulated truth has it there."""
    sim = world([particle((2000.0, 2000.0), d=2 * R)])
    sim._world.table.path_error[0] = 0.0
    u = np.asarray(direction, float) / np.linalg.norm(direction)
    v = np.array([-u[1], u[0]])
    start = np.array([2000.0, 2000.0]) - u * (R + TIP + LEAD) + v * offset
    block, codes = push(sim, start, start + 400.0 * u)
    nm = sim.config.codes_to_nm(codes)
    lifted = nm[:, 2] >= sim.config.lift - 1e-6
    monitor = PushMonitor(sim.config.preload, lever=sim._model.lever)
    monitor.set_baseline(block.s_n[lifted][:50], block.s_l[lifted][:50])
    kept = PushSignals(LEAD)
    kept.add(block.s_n, block.s_l, nm[:, :2], nm[:, 2] <= -0.999 * sim.config.preload, lifted)
    est = kept.angle(monitor.compensated, monitor.level, u, sim.params.scanner.scan_angle, sim._model.lever)
    (b,) = sim.truth()
    g = np.asarray(b.at) - (start + 400.0 * u)
    return est, math.degrees(math.atan2(float(g @ v), float(g @ u)))


@pytest.mark.parametrize("direction", [(1.0, 0.0), (0.0, 1.0), (0.6, 0.8), (-0.8, 0.6)])
@pytest.mark.parametrize("offset", [-20.0, -5.0, 5.0, 20.0])
def test_the_angle_from_the_forces_is_the_particles_on_the_tip(direction, offset):
    """Within 3.5° (about 3 nm across the line at the contact distance, 55 nm) and on the
    right side, whichever way the push runs across the cantilever."""
    est, true = _measured(direction, offset)
    assert est is not None and est.force > MIN_FORCE
    assert math.copysign(1.0, est.angle) == math.copysign(1.0, true)
    assert est.angle == pytest.approx(true, abs=3.5)
    assert 0.0 < est.std < 5.0
    lateral, std = est.lateral(R + TIP)
    assert lateral == pytest.approx((R + TIP) * math.sin(math.radians(true)), abs=3.5) and std > 0.0


def test_no_object_against_the_tip_gives_no_angle():
    """Friction alone, in the reference and the window: no contact force, no angle."""
    rng = np.random.default_rng(3)
    sn, sl = 0.5 + rng.normal(0, 0.005, 400), 0.3 + rng.normal(0, 0.005, 400)
    assert contact_angle(sn, sl, np.arange(100), np.arange(300, 400), (1.0, 0.0), 0.0, SEED_LEVER) is None
    assert contact_angle(sn, sl, np.arange(1), np.arange(300, 400), (1.0, 0.0), 0.0, SEED_LEVER) is None


@given(st.floats(-80.0, 80.0), st.floats(5.0, 60.0), st.floats(0.0, 360.0), st.floats(-180.0, 180.0))
def test_a_contact_force_built_from_an_angle_gives_that_angle_back(alpha, force, heading, psi):
    """Noise-free signals of a contact force at α from the motion, any motion, any scan
    angle: α comes back exactly (eq. 3.5, 3.6, 3.9 and R(ψ) inverted)."""
    from nanoasm.world.cantilever import signals_from_force, to_cantilever

    h = math.radians(heading)
    m = np.array([math.cos(h), math.sin(h)])
    a = h + math.radians(alpha)
    f_afm = -force * np.array([math.cos(a), math.sin(a)])
    fc = to_cantilever(np.array([[*f_afm, 10.0]]), psi)
    sn_w, sl_w = signals_from_force(fc, SEED_LEVER)
    sn_r, sl_r = signals_from_force(np.array([[0.0, 0.0, 10.0]]), SEED_LEVER)
    sn = np.concatenate([np.full(10, sn_r[0]), np.full(10, sn_w[0])])
    sl = np.concatenate([np.full(10, sl_r[0]), np.full(10, sl_w[0])])
    est = contact_angle(sn, sl, np.arange(10), np.arange(10, 20), m, psi, SEED_LEVER)
    assert est is not None and est.angle == pytest.approx(alpha, abs=1e-6) and est.force == pytest.approx(force)


def test_the_contact_onset_looked_for_near_the_start_only_ends_the_reference_where_it_did():
    """:func:`_onset` ``within`` share + SETTLE: the reference it ends (``min(share, onset -
    SETTLE)``) is the one the whole push's onset ends, to the last bit, where the force
    rises anywhere and where it rises within a smoothing length or two of where the search
    stops (the smoothing there reaches beyond it)."""
    from nanoasm.executor.contact_angle import SETTLE, SMOOTH, _onset

    rng = np.random.default_rng(8)
    ended = 0
    for trial in range(600):
        per_nm, share, force = rng.uniform(0.2, 4.0), rng.uniform(5.0, 60.0), rng.uniform(0.0, 3.0)
        rise = share + SETTLE + rng.uniform(-2 * SMOOTH, SMOOTH) if trial % 2 else rng.uniform(0.0, 120.0)
        along = np.cumsum(rng.uniform(0.5, 1.5, int(200 * per_nm)) / per_nm)
        along -= along[0]
        sn = rng.normal(0.0, 0.01, along.size) + np.where(along > rise, force * 0.05, 0.0)
        sl = rng.normal(0.0, 0.01, along.size) + np.where(along > rise, force * 0.03, 0.0)
        whole = min(share, _onset(sn, sl, along, SEED_LEVER) - SETTLE)
        assert min(share, _onset(sn, sl, along, SEED_LEVER, share + SETTLE) - SETTLE) == whole
        ended += whole < share
    assert ended > 100                                    # the onset ends many references early


def _stream(rng, monitor: PushMonitor, ahead: bool = False):
    """A push's chunks as a streamed push hands them over: lifted travel first, then
    samples pushing (a few in flight, below half the contact level), a contact force
    rising where the object is met, some lifted samples at the end. Yields ``(S_n, S_l,
    xy, pushing, lifted)`` per chunk, and sometimes new free-air baselines first.
    ``ahead``: the travel comes back from 1.5 µm ahead of the push, which speeds up as it
    goes (the lifted samples near the push's span, and the samples a nm, change as it
    grows)."""
    lead, n = rng.uniform(10.0, 40.0), int(rng.integers(200, 1500))
    length = rng.uniform(40.0, 300.0)
    x = np.linspace(-200.0, length, n) + rng.normal(0.0, 0.2, n)
    if ahead:                           # the object met within the reference: an onset
        lead, length = rng.uniform(4.0, 12.0), rng.uniform(300.0, 900.0)
        travel = n // 4
        x = np.concatenate([np.linspace(1500.0, -1.0, travel), length * np.linspace(0.0, 1.0, n - travel) ** 2])
        x[travel:] += rng.normal(0.0, 0.05, n - travel)
    y = rng.normal(0.0, 0.3, n) + 0.01 * x
    lifted = x < 0.0
    if ahead:
        lifted = np.arange(n) < travel
    lifted[-int(rng.integers(0, 20)):] = True
    pushing = ~lifted
    met = x > lead
    level = monitor.level
    jitter = 0.0005 if ahead else 0.05
    sn = np.where(lifted, 0.01, level * (1.0 + rng.normal(0.0, jitter, n)) + np.where(met, 0.02, 0.0))
    sn[pushing & (rng.random(n) < 0.05)] = 0.1 * level            # in flight: not in contact
    side = rng.uniform(0.1, 0.3) * rng.choice([-1.0, 1.0]) if ahead else rng.uniform(-0.3, 0.3)
    sl = rng.normal(0.3, 0.004, n) + np.where(met & pushing, side, 0.0) + 1e-4 * x
    i = 0
    while i < n:
        k = int(rng.integers(1, 150))
        yield slice(i, i + k), sn, sl, np.column_stack([x, y]), pushing, lifted
        i += k


@pytest.mark.parametrize("ahead", [False, True])
@pytest.mark.parametrize("seed", range(12))
def test_the_angle_read_as_the_samples_come_is_the_whole_computations(seed, ahead):
    """:meth:`PushSignals.angle` with the monitor's baseline key (each chunk compensated
    once, the contact samples and their distance along the push grown as they come, the
    windows read alone, the onset and the baseline's slope kept while what they read
    stays the same) gives the angle the whole computation gives from every sample, to the
    last bit, after every chunk: also when the free-air baselines change between reads
    (the key), and the level."""
    rng = np.random.default_rng(seed)
    monitor = PushMonitor(50.0, lever=SEED_LEVER)
    fast, whole = PushSignals(LEAD), PushSignals(LEAD)
    read = 0
    for sl_, sn, sl, xy, pushing, lifted in _stream(rng, monitor, ahead):
        if rng.random() < 0.05:
            monitor.set_baseline(sn[lifted][:30] + rng.normal(0, 0.01), sl[lifted][:30])
        for kept in (fast, whole):
            kept.add(sn[sl_], sl[sl_], xy[sl_], pushing[sl_], lifted[sl_])
        args = (monitor.compensated, monitor.level, (1.0, 0.01), 30.0, SEED_LEVER)
        got, want = fast.angle(*args, key=monitor.baseline_key), whole.angle(*args)
        assert got == want
        read += got is not None
    assert read > 0                            # angles were read, not only None


@given(st.lists(st.floats(-1e3, 1e3, allow_nan=False), min_size=2, max_size=400), st.integers(0, 3))
def test_a_windows_mean_and_standard_error_are_numpys(values, decimals):
    """:func:`_mean_std` gives ``x.mean()`` and ``x.std(ddof=1) / sqrt(n)`` to the bit (the
    angle's windows are read after every chunk of a tracked push)."""
    from nanoasm.executor.contact_angle import _mean_std

    for x in (np.array(values), np.round(np.array(values), decimals)):
        assert _mean_std(x) == (float(x.mean()), float(x.std(ddof=1)) / math.sqrt(x.size))
