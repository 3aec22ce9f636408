"""What lets a dry-run scale to a thousand objects keeps the simulated world as it was: the
creep of many moves summed as a power series, scan lines imaging only the bodies near
them, and the ``scaleN`` scene family."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nanoasm.world.families import SCALE_SIDE, family, family_case
from nanoasm.world.params import CreepParams, DriftParams
from nanoasm.world.render import make_surface, render_line, surface_near
from nanoasm.world.sim.contacts import SimContacts
from nanoasm.world.sim.creep_sum import MIN_FOLD, CreepSum
from nanoasm.world.sim.drift_model import DriftModel
from nanoasm.world.tipimage import Tip


def direct(t, times, steps, tau):
    """The creep sum as DriftModel made it before the fold: every move, blocks of 256."""
    t = np.asarray(t, float)
    acc = np.zeros((t.size, 2))
    for i in range(0, len(times), 256):
        dt = np.maximum(t[:, None] - times[None, i:i + 256], 0.0)
        acc += np.log10(1.0 + dt / tau) @ steps[i:i + 256]
    return acc


def moves(n, seed=1, gap=2.0):
    rng = np.random.default_rng(seed)
    return np.cumsum(rng.exponential(gap, n)), rng.normal(0.0, 2000.0, (n, 2))


def test_few_moves_are_summed_exactly_as_before():
    times, steps = moves(MIN_FOLD - 1)
    s = CreepSum(0.1)
    for t, step in zip(times, steps):
        s.add(t, step)
    q = times[-1] + np.linspace(0.0, 500.0, 300)
    assert np.array_equal(s(q), direct(q, times, steps, 0.1)) and s.folds == 0


def test_many_moves_fold_into_a_series_equal_to_the_sum_to_rounding():
    times, steps = moves(MIN_FOLD + 2000)
    s = CreepSum(0.13)
    for t, step in zip(times, steps):
        s.add(t, step)
    scale = np.abs(steps).sum()
    # a run's queries: chunks of samples going forward, a few in the past, one long span
    starts = [*np.arange(times[-1] - 400.0, times[-1] + 200.0, 1.7), 10.0, times[MIN_FOLD // 2], times[-1] - 3000.0]
    for t0 in starts:
        q = t0 + np.linspace(0.0, 0.8, 120)
        assert np.abs(s(q) - direct(q, times, steps, 0.13)).max() <= 1e-15 * scale
    q = np.linspace(0.0, times[-1], 500)
    assert np.abs(s(q) - direct(q, times, steps, 0.13)).max() <= 1e-15 * scale
    assert 0 < s.folds < len(starts) / 4            # the forward queries share their folds
    # a fold depends on the moves and the query alone: a fresh sum gives the same bits
    fresh = CreepSum(0.13)
    for t, step in zip(times, steps):
        fresh.add(t, step)
    q = times[-1] - 17.0 + np.linspace(0.0, 0.5, 50)
    assert np.array_equal(fresh(q), s(q))


def test_restored_moves_are_summed_anew():
    m = DriftModel(DriftParams((0.0, 0.0), 0.0), CreepParams(amplitude=0.01, tau=0.1), np.random.default_rng(1))
    m.record_move(1.0, 800.0, 0.0)
    before = m.creep(50.0)
    m.set_moves([1.0, 2.0], [(800.0, 0.0), (0.0, 900.0)])    # as world/sim/state.py restores
    after = m.creep(50.0)
    assert after[0] == pytest.approx(before[0]) and after[1] > 0
    assert after[1] == pytest.approx(0.01 * 900.0 * math.log10(1.0 + 48.0 / 0.1))


def test_a_scan_line_sees_the_same_heights_through_the_bodies_near_it():
    scene, _ = family_case("scale100", 3)
    tip = Tip()
    surface = make_surface(scene.objects, scene.obstacles, scene.area, rng=np.random.default_rng(2))
    units = list(scene.objects)
    cores = SimContacts(units, list(range(len(units)))).cores()
    rng = np.random.default_rng(4)
    seen = 0
    for _ in range(40):
        o = units[int(rng.integers(len(units)))]
        a = np.add(o.at, rng.normal(0.0, 150.0, 2))
        b = a + rng.normal(0.0, 300.0, 2)
        near = surface_near(surface, cores, np.minimum(a, b), np.maximum(a, b), tip=tip)
        assert len(near.bodies) < len(units) // 4
        seen += bool(near.bodies)
        full = render_line(surface, tuple(a), tuple(b), 200, tip=tip, rng=np.random.default_rng(5))
        part = render_line(near, tuple(a), tuple(b), 200, tip=tip, rng=np.random.default_rng(5))
        assert np.array_equal(full, part)
    assert seen >= 8


@pytest.mark.parametrize("n", [10, 100, 1000])
def test_scale_family_keeps_its_density_and_slots(n):
    scene, layout = family_case(f"scale{n}", 2)
    assert len(scene.objects) == n and len(layout.targets) == round(0.3 * n)
    assert scene.area[0] == pytest.approx(SCALE_SIDE * math.sqrt(n), abs=0.5)
    border = family(f"scale{n}").border
    for o in scene.objects:
        assert border <= o.at[0] <= scene.area[0] - border and border <= o.at[1] <= scene.area[1] - border


@pytest.mark.parametrize("name", ["scale1", "scale1001", "scale07", "scalex"])
def test_scale_family_names_out_of_range_are_refused(name):
    with pytest.raises(ValueError, match="scale"):
        family(name)


def test_times_summed_another_way_round_are_the_same_instant():
    """Issue 16: instrument times summed in another order differ in the last bits
    (5078.923 against 5078.923000000001); no clock comparison may take that for going
    back in time: the creep of the executor's filter (the crash), the filter itself, the
    simulator's drift and creep."""
    from nanoasm.drift import DriftFilter
    from nanoasm.drift.creep import CreepHistory, CreepModelParams

    t = 5078.923000000001
    before = 5078.923
    assert before < t
    h = CreepHistory(CreepModelParams())
    assert h.record(t, (900.0, 0.0)) and h.record(before, (0.0, 900.0))
    f = DriftFilter(epoch=0.0)
    f.measure(t, (1.0, 2.0), np.eye(2))
    f.predict_to(before)
    f.record_move(before, (800.0, 0.0))
    m = DriftModel(DriftParams((0.1, 0.0), 0.1), CreepParams(), np.random.default_rng(1), epoch=t)
    assert m.record_move(before, 900.0, 0.0)
    m.offset(before)
    m.offset(np.array([before, t]))


def test_a_large_scan_is_scored_in_bands_of_rows_alike(monkeypatch):
    """executor/windows.py makes a scan of more than BAND_PIXELS pixels in bands of rows
    when it sums windows (a 4000-pixel scan's whole transforms took 2 GB): the same
    windows, scores to rounding."""
    from nanoasm.executor import windows
    from nanoasm.instrument import HeightImage

    rng = np.random.default_rng(3)
    z = np.zeros((300, 260))
    for _ in range(60):
        i, j = rng.integers(0, 300), rng.integers(0, 260)
        z[max(i - 4, 0):i + 4, max(j - 4, 0):j + 4] += 50.0
    image = HeightImage(z + rng.normal(0.0, 0.3, z.shape), 10.0, (0.0, 0.0), "test", {})
    whole = windows.choose_windows(image, 400.0, count=4)
    monkeypatch.setattr(windows, "BAND_PIXELS", 5000)
    banded = windows.choose_windows(image, 400.0, count=4)
    assert [w.region for w in banded] == [w.region for w in whole]
    assert [w.score for w in banded] == pytest.approx([w.score for w in whole], rel=1e-9)


@pytest.mark.parametrize("k, step, shape, band", [(200, 25, (640, 700), 1 << 22), (203, 25, (600, 555), 40000),
                                                 (37, 4, (101, 87), 1 << 22), (8, 1, (20, 30), 100),
                                                 (64, 8, (64, 64), 1 << 22)])
def test_window_sums_on_the_grid_are_the_correlations_there(monkeypatch, k, step, shape, band):
    """executor/windows.py sums only the step grid's windows, block by block (the weight
    padded to whole blocks, the image made in bands of rows): the values the whole
    correlation has on the grid."""
    from scipy.signal import correlate
    from skimage.filters import window as taper

    from nanoasm.executor import windows

    rng = np.random.default_rng(k)
    h, w = rng.normal(size=shape), taper("hann", (k, k))
    monkeypatch.setattr(windows, "BAND_PIXELS", band)
    got = windows._window_sums(lambda r0, r1: h[r0:r1], shape, w, step)
    want = correlate(h, w, mode="valid", method="fft")[::step, ::step]
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9 * np.abs(want).max())


@pytest.mark.parametrize("margin", [0.0, 20.0])
def test_pixels_near_what_to_avoid_are_those_of_the_pointwise_test(margin):
    """executor/windows.py tests each part of what to avoid on the pixels of its box: the
    same mask as every pixel against the whole."""
    import shapely

    from nanoasm.executor import windows
    from nanoasm.instrument import HeightImage

    rng = np.random.default_rng(5)
    image = HeightImage(np.zeros((120, 150)), 10.0, (-35.0, 12.0), "test", {})
    avoid = shapely.union_all([shapely.LineString(rng.uniform(0, 1400, (2, 2))).buffer(rng.uniform(5, 40))
                               for _ in range(12)] + [shapely.box(100.0, 100.0, 300.0, 250.0)])
    x, y = image.pixel_centres()
    grown = avoid.buffer(margin) if margin > 0 else avoid
    want = shapely.contains_xy(grown, x[None, :], y[:, None]) | shapely.intersects_xy(avoid, x[None, :], y[:, None])
    got = windows._near(image, avoid, margin)
    assert want.sum() > 500 and (got == want).all()


def test_candidates_through_the_grid_are_those_of_every_unit():
    from nanoasm.world.sim import SimulatedAFM

    scene, _ = family_case("scale100", 1)
    world = SimulatedAFM(scene, seed=1)._world
    a, b, r = world.contacts.cores()
    rng = np.random.default_rng(7)
    for size in (10.0, 300.0, 3000.0, 20000.0):
        for _ in range(30):
            lo = rng.uniform(0.0, scene.area[0], 2)
            hi = lo + rng.uniform(0.0, size, 2)
            reach = rng.uniform(0.0, 200.0)
            hit = np.all((np.minimum(a, b) - (r + reach)[:, None] <= hi)
                         & (np.maximum(a, b) + (r + reach)[:, None] >= lo), axis=1)
            assert np.array_equal(world.candidates(lo, hi, reach), np.unique(world.contacts.groups[hit]))
