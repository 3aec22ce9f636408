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
