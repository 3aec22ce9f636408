"""The exact shortcuts of levelling a large image: order statistics between sampled bounds,
mask growth by shifted ORs, the surface fit's points picked row by row. Each must give,
to the bit, what the plain numpy or scipy call gives."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import ndimage

from nanoasm.world.identify import orderstats
from nanoasm.world.identify.levelling import centre_sigma, median


@pytest.fixture(params=[(8, 4.0), (8, 0.0), (64, 0.5)])
def small_select(request, monkeypatch):
    """Selection between sampled bounds on a few values, from a sample of a few values
    with wide or no margins (bounds that often miss the ranks)."""
    monkeypatch.setattr(orderstats, "SELECT_MIN", 2)
    monkeypatch.setattr(orderstats, "_SAMPLE", request.param[0])
    monkeypatch.setattr(orderstats, "_MARGIN", request.param[1])


def _same(got: float, want: float) -> bool:
    """Equal bits (NaN equal to NaN, 0.0 not -0.0)."""
    return np.float64(got).tobytes() == np.float64(want).tobytes() or (math.isnan(got) and math.isnan(want))


def _partitioned_median(values: np.ndarray) -> float:
    """The median as a partition at the two middle ranks gives it, NaN if any (which of
    two zeros it is may differ from ``np.median``'s, a partition at the upper rank only)."""
    n = values.size
    if n < 2:
        return float(values[0]) if n else math.nan
    h = n // 2
    part = np.partition(values, [h - 1, h])
    if np.isnan(part).any():
        return math.nan
    return float((part[h - 1] + part[h]) / 2) if n % 2 == 0 else float(part[h])


_values = st.lists(st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=64),
                             st.sampled_from([0.0, -0.0, 1.0, -1.0, 2.5])), min_size=0, max_size=400)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(_values, st.sampled_from([np.float64, np.float32]), st.integers(0, 2 ** 32 - 1))
def test_select_and_median_are_numpys_on_any_values(small_select, values, dtype, seed):
    """With ties, both zeros, NaN and infinities, in float64 and float32, all values or a
    mask's: the partition's elements at the ranks whenever :func:`select` answers, and
    ``np.median``'s value from :func:`median` (and the partition's sign of zero)."""
    with np.errstate(all="ignore"):
        a = np.array(values, dtype=np.float64).astype(dtype)
    keep = np.random.default_rng(seed).random(a.size) < 0.7
    for where, kept in ((None, a), (keep, a[keep])):
        if kept.size >= 2:
            h = kept.size // 2
            got = orderstats.select(a, (h - 1, h), where)
            part = np.partition(kept, [h - 1, h])
            if got is not None:
                assert all(g.dtype == dtype for g in got)
                assert np.array(got).tobytes() == part[[h - 1, h]].tobytes()
        with np.errstate(all="ignore"):                # inf + -inf
            want = np.median(kept) if kept.size else math.nan
            got, plain = median(a, where=where), _partitioned_median(kept)
        assert (math.isnan(got) and math.isnan(want)) or got == want
        assert _same(got, plain)


@pytest.mark.parametrize("n", [450_000, 450_001, 1_000_001, 3_000_000])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_select_answers_on_large_arrays_with_the_partitions_elements(n, dtype):
    """At the default sample size the bounds hold on large arrays (ties, a sorted run, a
    mask): the selection answers, with ``np.partition``'s elements; NaN makes it decline."""
    rng = np.random.default_rng(n)
    a = np.round(rng.normal(0.3, 1.0, n), 2).astype(dtype)     # no zero in the middle
    a[: n // 3] = np.sort(a[: n // 3])
    keep = rng.random(n) < 0.6
    for where, kept in ((None, a), (keep, a[keep])):
        h = kept.size // 2
        for ranks in ((h - 1, h), (h,), (kept.size // 1000, kept.size - 1 - kept.size // 1000)):
            got = orderstats.select(a, ranks, where)
            assert got is not None
            assert np.array(got).tobytes() == np.partition(kept, list(ranks))[list(ranks)].tobytes()
        centre = np.median(kept)
        assert median(a, where=where) == centre
        assert centre_sigma(a, where=where) == (centre, 1.4826 * float(np.median(np.abs(kept - centre))))
    a[rng.integers(n)] = np.nan
    assert orderstats.select(a, (n // 2,)) is None
    assert math.isnan(median(a))


def test_select_answers_or_declines_by_its_bounds(small_select):
    """Bounds that hold give the partition's elements; bounds that miss give no answer."""
    rng = np.random.default_rng(3)
    answered = 0
    for n in range(2, 3000, 7):
        a = rng.normal(0.0, 1.0, n)
        a[: n // 2] = np.sort(a[: n // 2])[::-1]
        h = n // 2
        got = orderstats.select(a, (h - 1, h))
        if got is not None:
            answered += 1
            assert np.array(got).tobytes() == np.partition(a, [h - 1, h])[[h - 1, h]].tobytes()
        assert median(a) == np.median(a)
    assert answered > 50


def test_select_declines_between_zeros_of_both_signs():
    """Which of 0.0 and -0.0 a partition puts at a rank is its own choice: no answer."""
    a = np.concatenate([np.full(200_000, -1.0), np.zeros(100_000), -np.zeros(100_000), np.ones(200_000)])
    np.random.default_rng(0).shuffle(a)
    assert orderstats.select(a, (299_999, 300_000)) is None
    assert orderstats.select(np.abs(a), (299_999, 300_000)) is not None
    assert _same(median(a), _partitioned_median(a)) and median(a) == np.median(a)


@settings(max_examples=100, deadline=None)
@given(st.integers(1, 40), st.integers(1, 40), st.integers(0, 5), st.floats(0.0, 1.0), st.integers(0, 2 ** 32 - 1))
def test_grow_square_is_the_maximum_filter(ny, nx, g, density, seed):
    """Shifted ORs along each axis: the maximum filter's booleans, edges and thin images included."""
    mask = np.random.default_rng(seed).random((ny, nx)) < density
    got = orderstats.grow_square(mask, g)
    assert got.dtype == bool and got is not mask
    np.testing.assert_array_equal(got, ndimage.maximum_filter(mask, size=2 * g + 1))


@pytest.mark.parametrize("seed", range(6))
def test_surface_points_picked_row_by_row_are_nonzeros(seed):
    """The picked points of the surface fit, found row by row (empty rows included), are
    those the index arrays of every pixel give."""
    from nanoasm.world.identify.levelling import _picked

    rng = np.random.default_rng(seed)
    use = rng.random((60 + seed, 50)) < 0.5
    use[rng.integers(0, use.shape[0], 8)] = False
    use[-1] = seed % 2 == 0
    iy, ix = np.nonzero(use)
    pick = np.linspace(0, iy.size - 1, 300 + 100 * seed).astype(int)
    got = _picked(use, np.count_nonzero(use, axis=1), pick)
    np.testing.assert_array_equal(got[0], iy[pick])
    np.testing.assert_array_equal(got[1], ix[pick])


@pytest.mark.parametrize("seed", range(3))
def test_level_with_selection_on_small_images_is_the_plain_computation(small_select, seed):
    """``level`` with every median selected between sampled bounds: the whole-image steps' result."""
    from test_identify import _plain_level

    from nanoasm.world.identify.levelling import level

    rng = np.random.default_rng(seed)
    ny, nx = 130 + 17 * seed, 110
    yy, xx = np.mgrid[0:ny, 0:nx]
    z = 0.01 * xx + 0.02 * yy + rng.normal(0, 0.3, (ny, nx)) + rng.normal(0, 2, ny)[:, None]
    for _ in range(20):
        cy, cx = rng.integers(0, ny), rng.integers(0, nx)
        z += 8 * np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / 50.0)
    if seed == 1:
        z[rng.random((ny, nx)) < 0.01] = np.nan
    for kw in ({}, {"line_order": 1}, {"grow": 3}):
        got = level(z, **kw)
        height, use, sigma = _plain_level(z, **kw)
        np.testing.assert_array_equal(got.height, height)
        np.testing.assert_array_equal(got.substrate, use)
        assert got.sigma == sigma


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 12), st.integers(1, 60), st.sampled_from([np.float64, np.float32]),
       st.sampled_from(["normal", "ties", "zeros", "special"]), st.integers(1, 4), st.floats(0.0, 3.0),
       st.integers(0, 2 ** 32 - 1))
def test_row_middles_are_each_rows_partition(ny, nx, dtype, kind, step, margin, seed):
    """Every row's two middle elements among its kept values, as a partition of that row
    alone puts them, wherever :func:`row_middles` answers (ties, both zeros, NaN, infinities,
    rows with fewer than two values; samples of every ``step``-th value, tight bounds)."""
    rng = np.random.default_rng(seed)
    z = {"normal": lambda: rng.normal(0.0, 1.0, (ny, nx)) + rng.normal(0.0, 3.0, (ny, 1)),
         "ties": lambda: rng.integers(-2, 3, (ny, nx)).astype(float),
         "zeros": lambda: rng.choice([0.0, -0.0, 1.0, -1.0], (ny, nx)),
         "special": lambda: rng.choice([np.nan, np.inf, -np.inf, 0.5, -0.5, 1.5], (ny, nx))}[kind]().astype(dtype)
    use = rng.random((ny, nx)) < rng.uniform(0.2, 1.0)
    counts = np.count_nonzero(use, axis=1)
    old = orderstats._ROW_STEP, orderstats._ROW_MARGIN
    orderstats._ROW_STEP, orderstats._ROW_MARGIN = step, margin
    try:
        a, b, ok = orderstats.row_middles(z, use, counts)
    finally:
        orderstats._ROW_STEP, orderstats._ROW_MARGIN = old
    assert ok.shape == (ny,) and not ok[counts < 2].any()
    for i in np.flatnonzero(ok):
        h = counts[i] // 2
        part = np.partition(z[i, use[i]], [h - 1, h])
        assert a[i].tobytes() == part[h - 1].tobytes() and b[i].tobytes() == part[h].tobytes()


@pytest.mark.parametrize("seed", range(3))
def test_row_offsets_on_a_large_image_are_each_rows_median(seed):
    """The rows' offsets of a large image, most rows partitioned at once: the medians of
    each row's kept values one by one, interpolated over rows with too few (NaN in a row,
    a row of integers, a row of zeros of both signs)."""
    from nanoasm.world.identify.levelling import _row_offsets

    rng = np.random.default_rng(seed)
    ny, nx = 300, 900 + seed
    z = rng.normal(0.0, 1.0, (ny, nx)) + rng.normal(0.0, 3.0, (ny, 1))
    use = rng.random((ny, nx)) < 0.8
    use[5] = False
    use[7, 4:] = False
    z[9, 4] = np.nan
    z[11] = np.round(z[11])
    z[13] = rng.choice([0.0, -0.0], nx)
    z[13, ::3] = rng.normal(0.0, 1.0, z[13, ::3].size)
    assert z.size >= orderstats.SELECT_MIN
    counts = np.count_nonzero(use, axis=1)
    assert np.count_nonzero(orderstats.row_middles(z, use, counts)[2]) > ny // 2
    offs = np.full(ny, np.nan)
    for i in np.flatnonzero(counts >= 5):
        offs[i] = _partitioned_median(z[i, use[i]])
    good = np.isfinite(offs)
    want = np.interp(np.arange(ny), np.flatnonzero(good), offs[good])
    assert _row_offsets(z, use).tobytes() == want.tobytes()



@pytest.mark.parametrize("holes", [False, True])
def test_tilt_is_the_medians_of_the_valid_differences(small_select, holes):
    """The slopes and the noise from differences written into a scratch array and masked
    there: the medians of the differences between valid neighbours, gathered."""
    from nanoasm.world.identify.levelling import _tilt

    rng = np.random.default_rng(7)
    ny, nx = 90, 70
    z = 0.03 * np.arange(nx)[None, :] - 0.02 * np.arange(ny)[:, None] + rng.normal(0.0, 0.2, (ny, nx))
    valid = rng.random((ny, nx)) > (0.05 if holes else 0.0)
    z = np.where(valid, z, np.nan) if holes else z
    dx = np.diff(z, axis=1)[valid[:, 1:] & valid[:, :-1]]
    dy = np.diff(z, axis=0)[valid[1:] & valid[:-1]]
    with np.errstate(invalid="ignore"):
        got = _tilt(z, valid if holes else None, np.empty(z.size))
    assert got == (np.median(dx), np.median(dy), 1.4826 * float(np.median(np.abs(dx - np.median(dx)))) / np.sqrt(2))


def test_initial_substrate_on_plateaus_is_the_same_by_selection_or_partition(monkeypatch):
    """An image two thirds covered by a plateau starts from the lower level; the mask is
    the same whether its medians are selected between bounds or partitioned whole, and
    whether the scratch array is the caller's or its own."""
    from nanoasm.world.identify.levelling import initial_substrate

    rng = np.random.default_rng(8)
    ny, nx = 300, 1000
    z = 0.001 * np.arange(nx)[None, :] + rng.normal(0.0, 0.05, (ny, nx))
    z[:, 300:] += 20.0
    valid = np.isfinite(z)
    assert z.size >= orderstats.SELECT_MIN
    selected = initial_substrate(z, valid, out=np.empty(z.size))
    assert 0.25 < selected.mean() < 0.35
    monkeypatch.setattr(orderstats, "SELECT_MIN", z.size + 1)
    np.testing.assert_array_equal(initial_substrate(z, valid), selected)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.integers(2, 3000), st.floats(0.1, 0.9), st.integers(0, 2 ** 32 - 1))
def test_centre_sigma_leaves_the_deviations_in_out(small_select, n, share, seed):
    """``out`` holds every value's absolute deviation from the median (what the levelling's
    mask reads), the values stay as they were, and the figures are those without ``out``."""
    rng = np.random.default_rng(seed)
    values = np.round(rng.normal(0.0, 3.0, (3, n)), 1)
    where = rng.random(values.shape) < share
    where.flat[0] = True
    for keep in (where, None):
        before, out = values.copy(), np.empty_like(values)
        got = centre_sigma(values, where=keep, out=out)
        assert got == centre_sigma(values.copy(), where=keep)
        assert values.tobytes() == before.tobytes()
        assert out.tobytes() == np.abs(values - got[0]).tobytes()
