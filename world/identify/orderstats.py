"""Exact order statistics and mask growth on whole images, without image-sized copies.

:func:`select` finds the values of given ranks among many (all of them, or those a mask
keeps) from the few between two bounds read off a strided sample; :func:`grow_square`
dilates a mask by a square with shifted ORs. Both give, to the bit, what ``np.partition``
and ``ndimage.maximum_filter`` give, in a fraction of their time on a large image.
"""

from __future__ import annotations

import math

import numpy as np

#: Fewer values than this are left to ``np.partition`` (:func:`select` returns None).
SELECT_MIN = 1 << 18
#: About this many values sampled for the bounds.
_SAMPLE = 1 << 16
#: The bounds lie this many square roots of the sample's size beyond the wanted ranks.
_MARGIN = 4.0
#: A row's bounds come from every this many-th of its values, ...
_ROW_STEP = 8
#: ... this many square roots of their number beyond the wanted ranks (a row whose
#: bounds miss, one in twenty, takes its own partition).
_ROW_MARGIN = 1.0


def select(values: np.ndarray, ranks: tuple[int, ...], where: np.ndarray | None = None) -> list | None:
    """The values of the ascending 0-based ``ranks`` among ``values`` (flattened; only those
    ``where`` keeps, a mask of their shape), as numpy scalars: the elements ``np.partition``
    puts at those ranks, bit for bit. None when there are fewer than ``SELECT_MIN`` values,
    when the sampled bounds miss a rank, when a value is NaN, or when the values equal to a
    selected zero differ in sign (then which one a partition puts there is its own choice).

    Values below the lower bound are counted, those above the upper one are counted, and
    only those between (a few percent) are partitioned; the three counts must add up to
    all the values, which NaN (neither below, between nor above) prevents.
    """
    values = np.ravel(values)
    keep = None if where is None else np.ravel(where)
    n = values.size if keep is None else int(np.count_nonzero(keep))
    if n < SELECT_MIN:
        return None
    step = max(1, values.size // _SAMPLE)
    sample = values[::step] if keep is None else values[::step][keep[::step]]
    if sample.size < 2:
        return None
    sample = np.sort(sample)
    m = sample.size
    margin = int(_MARGIN * math.sqrt(m)) + 1
    lo = sample[max(ranks[0] * m // n - margin, 0)]
    hi = sample[min(ranks[-1] * m // n + margin, m - 1)]
    if not lo <= hi:                            # a NaN bound
        return None
    below = np.less(values, lo)
    inside = np.less_equal(values, hi)
    above = np.greater(values, hi)
    if keep is not None:
        below &= keep
        inside &= keep
        above &= keep
    inside ^= below                             # lo <= v <= hi: below lies within v <= hi
    n_below, n_inside = int(np.count_nonzero(below)), int(np.count_nonzero(inside))
    if n_below + n_inside + int(np.count_nonzero(above)) != n:
        return None                             # NaN
    if not n_below <= ranks[0] <= ranks[-1] < n_below + n_inside:
        return None
    mid = values[inside]
    mid.partition([r - n_below for r in ranks])
    picked = [mid[r - n_below] for r in ranks]
    if any(p == 0 for p in picked):
        signs = np.signbit(mid[mid == 0])
        if signs.any() and not signs.all():
            return None
    return picked


def grow_square(mask: np.ndarray, g: int) -> np.ndarray:
    """A 2-D boolean ``mask`` grown by ``g`` pixels in each of the 8 directions: a new array,
    ``ndimage.maximum_filter(mask, size=2 * g + 1)`` (the window clipped at the edges, which
    its reflection at the edges comes to), one shifted OR a pixel of reach along each axis."""
    rows = mask.copy()
    for s in range(1, g + 1):
        rows[:, s:] |= mask[:, :-s]
        rows[:, :-s] |= mask[:, s:]
    out = rows.copy()
    for s in range(1, g + 1):
        out[s:] |= rows[:-s]
        out[:-s] |= rows[s:]
    return out


def row_middles(z: np.ndarray, use: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row ``i`` of the 2-D ``z``, the elements at ranks ``counts[i] // 2 - 1`` and
    ``counts[i] // 2`` among ``z[i, use[i]]`` (``counts``: ``use``'s per row), those
    ``np.partition`` puts there, and which rows have them: not those with fewer than 2
    values, with bounds that miss, with NaN or with a selected zero (:func:`select`).

    The bounds come from every ``_ROW_STEP``-th column of the row; the values between
    them, shifted so that every row's wanted ranks fall in the same two columns (padded
    with infinities), are partitioned at once.
    """
    ny, nx = z.shape
    h, rows = counts // 2, np.arange(ny)
    picked = use[:, ::_ROW_STEP]
    sample = np.where(picked, z[:, ::_ROW_STEP], np.inf)
    sample.sort(axis=1)
    m = np.count_nonzero(picked, axis=1)
    margin = (_ROW_MARGIN * np.sqrt(m)).astype(np.intp) + 1
    last, total = np.maximum(m - 1, 0), np.maximum(counts, 1)
    lo = sample[rows, np.clip((h - 1) * m // total - margin, 0, last)][:, None]
    hi = sample[rows, np.clip(h * m // total + margin, 0, last)][:, None]
    below, inside = z < lo, z <= hi
    below &= use
    inside &= use
    inside ^= below
    n_below, n_inside = np.count_nonzero(below, axis=1), np.count_nonzero(inside, axis=1)
    want = h - 1 - n_below                      # the lower rank among the row's values between
    ok = (counts >= 2) & (m >= 2) & (want >= 0) & (want + 1 < n_inside)
    if np.isnan(z).any():                       # NaN is neither below, between nor above
        above = z > hi
        above &= use
        ok &= n_below + n_inside + np.count_nonzero(above, axis=1) == counts
    inside &= ok[:, None]
    n_inside, want = np.where(ok, n_inside, 0), np.where(ok, want, 0)
    if not ok.any():
        return np.zeros(ny, z.dtype), np.zeros(ny, z.dtype), ok
    k = int(want.max())
    shift = k - want                            # -inf in front of row i: its ranks move to k, k + 1
    width = int((shift + n_inside).max())
    at = np.repeat(rows * width + shift - (np.cumsum(n_inside) - n_inside), n_inside) + np.arange(n_inside.sum())
    part = np.full((ny, width), np.inf, z.dtype)
    part[np.arange(width)[None, :] < shift[:, None]] = -np.inf
    part.ravel()[at] = z[inside]
    part.partition([k, k + 1], axis=1)
    a, b = part[:, k], part[:, k + 1]
    ok &= (a != 0) & (b != 0)                   # a zero: which one is the partition's choice
    return a, b, ok
