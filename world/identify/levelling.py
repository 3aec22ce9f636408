"""Levelling a raw height image so that the bare substrate sits at z = 0.

A polynomial surface (a plane by default) is fitted to the substrate and subtracted,
then every scan line (row) is aligned by its median (or a low-order polynomial) over
the substrate. Objects would bias both fits, so they are masked out and the fits
repeated: each round marks what stands clearly above (or sinks clearly below) the
substrate, grows that mask by a few pixels to cover the tip-broadened skirts, and fits
again on what is left. When flat plateaus (electrodes) cover much of the image, the
first round starts from the lowest extended level instead (:func:`initial_substrate`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .orderstats import SELECT_MIN, grow_square, row_middles, select

#: Robust sigma from the median absolute deviation of a normal distribution.
MAD_TO_SIGMA = 1.4826
#: Lowest automatic cut (nm): a cut closer to the substrate finds noise, not objects.
CUT_FLOOR = 0.5
#: A height level holding at least this fraction of the image may be the substrate (5 %:
#: the two electrode pads of a bowtie hold 7 % of its image but most of their rows).
DENSE_LEVEL = 0.05
#: ... and the lowest such level is the substrate only if this fraction of rows shows it.
ROWS_WITH_SUBSTRATE = 0.8
#: Rows of a fitted surface evaluated at once (a band of a 4000-pixel image is 2 MB).
_BAND = 64
#: Rows of a band in passes made band by band only to spare an image-sized copy.
COPY_BAND = 256


@dataclass(frozen=True, eq=False)
class Levelled:
    """A levelled image: ``height`` (nm, substrate at 0), the ``substrate`` mask used
    by the last fit, the substrate's robust noise ``sigma`` (nm) and ``valid`` (finite
    input pixels; invalid ones are set to 0)."""

    height: np.ndarray
    substrate: np.ndarray
    sigma: float
    valid: np.ndarray


def _powers(order: int) -> list[tuple[int, int]]:
    return [(i, j) for i in range(order + 1) for j in range(order + 1 - i)]


def _surface_terms(z: np.ndarray, use: np.ndarray, order: int, max_points: int) -> list | None:
    """The least-squares polynomial's terms (coefficient, rows' and columns' powers, None
    for a power 0: ones), or None where ``use`` holds too few pixels to fit it."""
    ny, nx = z.shape
    counts = np.count_nonzero(use, axis=1)
    total = int(counts.sum())
    if total < (order + 1) * (order + 2):
        return None
    if total > max_points:                     # the points np.nonzero's row-major order picks, row by row
        iy, ix = _picked(use, counts, np.linspace(0, total - 1, max_points).astype(int))
    else:
        iy, ix = np.nonzero(use)
    xs, ys = np.linspace(-1.0, 1.0, nx), np.linspace(-1.0, 1.0, ny)
    powers = _powers(order)
    a = np.stack([xs[ix] ** i * ys[iy] ** j for i, j in powers], axis=-1)
    coef, *_ = np.linalg.lstsq(a, z[iy, ix], rcond=None)
    return [(k, ys ** j if j else None, xs ** i if i else None) for (i, j), k in zip(powers, coef)]


def _picked(use: np.ndarray, counts: np.ndarray, pick: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(iy[pick], ix[pick])`` of ``iy, ix = np.nonzero(use)`` (``counts``: ``use``'s per
    row; ``pick`` ascending), without the index arrays of every pixel."""
    starts = np.cumsum(counts) - counts        # the rank of each row's first pixel
    iy = np.searchsorted(starts, pick, side="right") - 1     # an empty row starts where the next does
    ix = np.empty_like(pick)
    edges = np.flatnonzero(np.diff(iy)) + 1
    for a, b in zip(np.concatenate([[0], edges]), np.concatenate([edges, [pick.size]])):
        r = iy[a]
        ix[a:b] = np.flatnonzero(use[r])[pick[a:b] - starts[r]]
    return iy, ix


def _band(band: np.ndarray, r: int, terms: list) -> np.ndarray:
    """The surface's rows ``r`` on into ``band`` (zeroed first): each term ``k * np.outer(yj,
    xi)`` added in turn, a factor of ones broadcast instead (1.0 * v is v: the same sums)."""
    band[...] = 0.0
    for k, yj, xi in terms:
        if yj is None:
            band += k if xi is None else k * xi
        elif xi is None:
            band += (k * yj[r:r + band.shape[0]])[:, None]
        else:
            band += k * np.outer(yj[r:r + band.shape[0]], xi)
    return band


def fit_surface(z: np.ndarray, use: np.ndarray, order: int, max_points: int = 40000) -> np.ndarray:
    """Least-squares 2-D polynomial of total degree ``order`` through ``z[use]``, evaluated everywhere."""
    out = np.zeros_like(z)
    terms = _surface_terms(z, use, order, max_points)
    for r in range(0, z.shape[0], _BAND) if terms else ():     # band by band: the same sums, in cache
        _band(out[r:r + _BAND], r, terms)
    return out


def _subtract_surface(z: np.ndarray, use: np.ndarray, order: int, max_points: int = 40000) -> None:
    """``z -= fit_surface(z, use, order)`` to the bit, a band at a time (no image-sized surface)."""
    terms = _surface_terms(z, use, order, max_points)
    if not terms:
        return
    buf = np.empty((_BAND, z.shape[1]), z.dtype)
    for r in range(0, z.shape[0], _BAND):
        rows = z[r:r + _BAND]
        rows -= _band(buf[:rows.shape[0]], r, terms)


def align_rows(z: np.ndarray, use: np.ndarray, order: int = 0, min_count: int = 5) -> np.ndarray:
    """Per-row correction: the median (``order`` 0) or a polynomial fit over ``use`` pixels.

    Rows with fewer than ``min_count`` usable pixels take the offset interpolated from
    their neighbours (their polynomial terms beyond the offset are dropped).
    """
    ny, nx = z.shape
    if order == 0:
        filled = _row_offsets(z, use, min_count)
        return np.zeros_like(z) if filled is None else np.broadcast_to(filled[:, None], z.shape).copy()
    corr = np.zeros_like(z)
    offs = np.full(ny, np.nan)
    xs = np.linspace(-1.0, 1.0, nx)
    counts = np.count_nonzero(use, axis=1)
    for i in range(ny):
        u = use[i]
        if counts[i] < max(min_count, order + 2):
            continue
        c = np.polynomial.polynomial.polyfit(xs[u], z[i, u], order)
        corr[i] = np.polynomial.polynomial.polyval(xs, c)
        offs[i] = np.median(corr[i])
        corr[i] -= offs[i]
    good = np.isfinite(offs)
    if not good.any():
        return corr
    filled = np.interp(np.arange(ny), np.nonzero(good)[0], offs[good])
    return corr + filled[:, None]


def _row_offsets(z: np.ndarray, use: np.ndarray, min_count: int = 5) -> np.ndarray | None:
    """:func:`align_rows`' order-0 correction as one offset a row (None: no row has
    ``min_count`` usable pixels): each row's median over ``use``, interpolated between."""
    offs = np.full(z.shape[0], np.nan)
    counts = np.count_nonzero(use, axis=1)
    enough = counts >= min_count
    if z.size >= SELECT_MIN:                  # most rows at once: median's arithmetic on the same elements
        a, b, done = row_middles(z, use, counts)
        done &= enough
        with np.errstate(invalid="ignore", over="ignore"):
            offs[done] = np.where(counts % 2 == 0, (a + b) / 2, b)[done]
        enough &= ~done
    for i in np.flatnonzero(enough):          # nanmedian's value, no copies
        offs[i] = median(z[i, use[i]])
    good = np.isfinite(offs)
    if not good.any():
        return None
    return np.interp(np.arange(z.shape[0]), np.nonzero(good)[0], offs[good])


def median(values: np.ndarray, *, where: np.ndarray | None = None, overwrite: bool = False) -> float:
    """``np.median``'s value (flattened; ``where``: of the values that mask keeps), without
    its third selection (numpy adds the last element to check for NaN; here the upper
    half's maximum does) and, on many values, from the few between sampled bounds
    (:func:`.orderstats.select`, the same two elements): a row's median without numpy's
    dispatch, an image's without a copy of it.
    ``overwrite``: reorder ``values`` (a contiguous array the caller gives up) in place
    instead of a copy of them when they are partitioned whole."""
    values = np.asarray(values)
    n = values.size if where is None else int(np.count_nonzero(where))
    if n < 2:
        values = np.ravel(values) if where is None else np.ravel(values)[np.ravel(where)]
        return float(values[0]) if n else math.nan
    h = n // 2
    part = select(values, (h - 1, h), where)
    if part is None:
        if where is not None:
            values, overwrite = np.ravel(values)[np.ravel(where)], True
        values = np.ravel(values)
        if overwrite:
            values.partition([h - 1, h])
            part = values
        else:
            part = np.partition(values, [h - 1, h])
        if np.isnan(part[h:].max()):           # NaNs sort last
            return math.nan
        part = [part[h - 1], part[h]]
    return float((part[0] + part[1]) / 2) if n % 2 == 0 else float(part[1])


def centre_sigma(values: np.ndarray, *, where: np.ndarray | None = None, overwrite: bool = False,
                 out: np.ndarray | None = None) -> tuple[float, float]:
    """The median of ``values`` (``where``: of those that mask keeps) and their
    normal-equivalent sigma from the median absolute deviation (``overwrite``:
    ``values``, contiguous, are the caller's to overwrite; ``out``: an array of their
    shape left holding every value's absolute deviation from the median)."""
    if (values.size if where is None else np.count_nonzero(where)) == 0:
        return math.nan, 0.0
    centre = median(values, where=where, overwrite=overwrite)
    dev = np.subtract(values, centre, out=out if out is not None else values if overwrite else None)
    return centre, float(MAD_TO_SIGMA * median(np.abs(dev, out=dev), where=where, overwrite=out is None))


def robust_sigma(values: np.ndarray) -> float:
    """Normal-equivalent sigma from the median absolute deviation."""
    return centre_sigma(values)[1]


def _tilt(z: np.ndarray, valid: np.ndarray | None, out: np.ndarray) -> tuple[float, float, float]:
    """The sample's tilt, the median slopes along the rows and along the columns between
    valid neighbours (``valid`` None: all are), and the noise sigma of a height from the
    differences along the rows (0 with no pair); ``out`` (as many elements as ``z``)
    holds the differences.

    Flat substrate and flat plateaus share the tilt, objects' flanks cancel and steps
    are rare, so the medians hold however much of the image the plateaus cover.
    """
    ny, nx = z.shape
    pairs = None if valid is None else valid[:, 1:] & valid[:, :-1]
    dx = np.subtract(z[:, 1:], z[:, :-1], out=out[:ny * (nx - 1)].reshape(ny, nx - 1))    # np.diff's
    sx, noise = 0.0, 0.0
    if (dx.size if pairs is None else np.count_nonzero(pairs)):
        sx, sigma = centre_sigma(dx, where=pairs, overwrite=True)
        noise = sigma / np.sqrt(2)
    pairs = None if valid is None else valid[1:] & valid[:-1]
    dy = np.subtract(z[1:], z[:-1], out=out[:(ny - 1) * nx].reshape(ny - 1, nx))
    sy = median(dy, where=pairs) if (dy.size if pairs is None else np.count_nonzero(pairs)) else 0.0
    return sx, sy, noise


def _untilted(z: np.ndarray, sx: float, sy: float, out: np.ndarray) -> np.ndarray:
    """``z`` less the plane of slopes ``sx``, ``sy`` through 0, in ``out`` (of ``z``'s shape)."""
    ny, nx = z.shape
    np.add(sx * np.arange(nx)[None, :], sy * np.arange(ny)[:, None], out=out)
    return np.subtract(z, out, out=out)


def initial_substrate(z: np.ndarray, valid: np.ndarray, *, out: np.ndarray | None = None) -> np.ndarray:
    """Pixels to start levelling from: all valid ones, unless plateaus hold a large part.

    The heights, less the tilt (:func:`_tilt`), are binned at the noise
    level (from differences of neighbours along the rows). Levels holding at least
    ``DENSE_LEVEL`` of the pixels are candidate substrates; objects rest on the
    substrate, so when there are several the lowest is it, and the start excludes
    everything closer to the next level up, provided most rows show that level (else
    the levels are bands of offset lines). Row medians alone would otherwise take a
    plateau covering most of a row for the substrate. ``out``: a scratch array of
    ``z``'s size and type (else a new one).
    """
    out = np.empty(z.size, z.dtype) if out is None else out
    every = bool(valid.all())
    sx, sy, noise = _tilt(z, None if every else valid, out)
    flat = _untilted(z, sx, sy, out.reshape(z.shape))
    vals = flat.ravel() if every else flat.ravel()[valid.ravel()]
    if noise <= 0 or vals.size < 100:
        return valid
    lo, hi = np.percentile(vals, [0.1, 99.9], overwrite_input=True)     # reorders vals: flat is made again
    step = max(noise, (hi - lo) / 4000)
    if hi - lo < 10 * noise:
        return valid
    hist, edges = np.histogram(vals, bins=np.arange(lo, hi + step, step))
    smooth = ndimage.uniform_filter1d(hist.astype(float), 3)
    centres = 0.5 * (edges[:-1] + edges[1:])
    cum = np.concatenate([[0], np.cumsum(hist)])
    half = max(1, int(round(3 * noise / step)))
    levels: list[tuple[float, int]] = []
    for i in range(1, len(smooth) - 1):
        if smooth[i] >= smooth[i - 1] and smooth[i] > smooth[i + 1]:
            mass = int(cum[min(i + half + 1, len(hist))] - cum[max(i - half, 0)])
            if mass >= DENSE_LEVEL * vals.size:
                levels.append((float(centres[i]), mass))
    separate = max(10 * noise, 2.0)
    merged: list[tuple[float, int]] = []
    for h, m in levels:
        if merged and h - merged[-1][0] < separate:
            if m > merged[-1][1]:
                merged[-1] = (h, m)
            continue
        merged.append((h, m))
    if len(merged) < 2:
        return valid
    (h0, _), (h1, _) = merged[0], merged[1]
    flat = np.subtract(_untilted(z, sx, sy, flat), h0, out=flat)
    start = valid & (np.abs(flat, out=flat) <= (h1 - h0) / 2)
    # Levels that each fill whole rows are line offsets (bands), not plateaus on a
    # substrate: the row alignment handles those, starting from every pixel.
    if np.mean(np.count_nonzero(start, axis=1) >= 5) < ROWS_WITH_SUBSTRATE:
        return valid
    return start


def level(height: np.ndarray, *, plane_order: int = 1, line_order: int = 0,
          iterations: int = 6, k_mask: float = 3.0, grow: int = 2,
          floor: float = CUT_FLOOR) -> Levelled:
    """Level ``height`` (nm) so that the substrate is at 0.

    Parameters
    ----------
    height : (ny, nx) float array
        Raw heights; non-finite pixels are ignored and come back as 0.
    plane_order : int
        Degree of the 2-D polynomial removed first (0: none beyond an offset).
    line_order : int
        0 aligns each row by its median, 1 or 2 by a polynomial along the row.
    iterations : int
        Most rounds of fit, mask, fit again (fewer once the mask stops changing).
    k_mask : float
        Pixels further than ``max(k_mask * sigma, floor / 2)`` from the substrate are masked.
    grow : int
        Pixels by which the object mask is grown.
    """
    z = np.asarray(height, dtype=float)
    if z.ndim != 2:
        raise ValueError(f"height must be 2-D, got shape {z.shape}")
    if plane_order < 0 or line_order not in (0, 1, 2) or iterations < 1 or grow < 0:
        raise ValueError("plane_order >= 0, line_order in (0, 1, 2), iterations >= 1, grow >= 0 required")
    valid = np.isfinite(z)
    if not valid.any():
        raise ValueError("height has no finite value")
    every = bool(valid.all())
    z = z.copy(order="K") if every else np.where(valid, z, median(z, where=valid))     # np.where's layout
    scratch = np.empty(z.shape)               # one image-sized buffer for every step's temporaries
    use = initial_substrate(z, valid, out=scratch.ravel())
    sigma = 0.0
    for _ in range(iterations):               # z is this function's own: changed in place
        _subtract_surface(z, use, plane_order)
        if line_order == 0:
            rows = _row_offsets(z, use)
            if rows is not None:
                z -= rows[:, None]
        else:
            z -= align_rows(z, use, line_order)
        centre, sigma = centre_sigma(z, where=use, out=scratch)     # scratch: |z - centre|
        z -= centre
        limit = max(k_mask * sigma, floor / 2)
        objects = scratch > limit
        if grow:                              # = binary_dilation(objects, 3 x 3, iterations=grow)
            objects = grow_square(objects, grow)
        new_use = valid & ~objects
        if np.count_nonzero(new_use) < max(10, 0.05 * z.size):
            break                             # too little substrate left: keep the last mask
        if np.count_nonzero(new_use != use) <= 1e-3 * z.size:
            use = new_use
            break                             # converged
        use = new_use
    if not every:
        z[~valid] = 0.0
    return Levelled(z, use, sigma, valid)


def default_cut(lev: Levelled, k: float = 5.0, floor: float = CUT_FLOOR) -> float:
    """Cut height: the substrate's mode plus ``k`` robust sigmas, never below ``floor`` nm.

    The mode is the peak of the height histogram of the substrate pixels (bins of a
    fifth of sigma, lightly smoothed).
    """
    sigma = lev.sigma
    mode = 0.0
    if np.count_nonzero(lev.substrate) > 100 and sigma > 0:
        bins = np.arange(-5 * sigma, 5 * sigma + sigma / 5, sigma / 5)
        hist, edges = 0, bins                 # the substrate's histogram summed band by band: no copy of it
        for r in range(0, lev.height.shape[0], _BAND):
            part, edges = np.histogram(lev.height[r:r + _BAND][lev.substrate[r:r + _BAND]], bins=bins)
            hist = hist + part
        hist = ndimage.uniform_filter1d(hist.astype(float), 3)
        i = int(np.argmax(hist))
        mode = 0.5 * (edges[i] + edges[i + 1])
    return max(floor, mode + k * sigma)
