"""The substrate under a scan line's profile: the straight line (a tilted sample) fitted
to the samples that lie well below the object, found by iterating from a low quantile (or
from the substrate other lines measured), and the robust spread of the samples about it.
"""

from __future__ import annotations

import math

import numpy as np

from nanoasm.param import number
from nanoasm.world.identify.levelling import centre_sigma, median

#: Largest height magnitude accepted in a profile (nm); larger is not a height.
MAX_HEIGHT = 1e9


def _check_profile(profile) -> np.ndarray:
    z = np.asarray(profile, dtype=float)
    if z.ndim != 1 or z.size < 5:
        raise ValueError(f"profile must be a 1-D array of at least 5 heights, got shape {z.shape}")
    if not np.all(np.isfinite(z)):
        raise ValueError("profile must hold finite heights (NaN or inf found)")
    if np.abs(z).max() > MAX_HEIGHT:
        raise ValueError(f"profile heights must be below {MAX_HEIGHT:g} nm in magnitude")
    return z


def _dilate(mask: np.ndarray, k: int) -> np.ndarray:
    if k <= 0 or not mask.any():
        return mask
    c = np.concatenate([[0], np.cumsum(mask, dtype=np.int64)])
    n = mask.size
    i = np.arange(n)
    lo, hi = np.maximum(i - k, 0), np.minimum(i + k + 1, n)
    return (c[hi] - c[lo]) > 0


def _robust_std(r: np.ndarray) -> float:
    """1.4826 x the median absolute deviation (``np.median``'s values, a third fewer selections)."""
    return centre_sigma(r)[1] if r.size >= 2 else 0.0


def fit_baseline(profile, spacing: float, height: float, *, band: float = 0.15,
                 iterations: int = 8, start: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Substrate line under a profile and the noise about it.

    Parameters
    ----------
    profile : (n,) array
        Heights (nm), finite.
    spacing : float
        Distance between samples (nm).
    height : float
        Expected object height (nm); samples more than ``band * height`` above the
        current baseline (and a guard of the same lateral size) count as object.
    band : float
        Fraction of ``height`` that separates substrate from object, in (0, 1).
    iterations : int
        Most refits; stops earlier once the substrate samples do not change.
    start : (n,) array, optional
        The substrate to begin from; the profile's 2nd percentile, flat, when not given.

    Returns
    -------
    baseline : (n,) array
        Substrate height under every sample (nm).
    noise : float
        Robust rms of the substrate samples about the baseline (nm).
    """
    z = _check_profile(profile)
    spacing = number("spacing", spacing, positive=True)
    height = number("height", height, positive=True)
    if not 0 < band < 1:
        raise ValueError(f"band must be in (0, 1), got {band}")
    n = z.size
    x = np.arange(n, dtype=float)
    guard = math.ceil(band * height / spacing)
    base = np.full(n, np.percentile(z, 2.0)) if start is None else np.asarray(start, float)
    substrate = np.ones(n, bool)
    for it in range(iterations):
        sub = ~_dilate(z - base > band * height, guard)
        if sub.sum() < 3:
            break
        if it and np.array_equal(sub, substrate):
            break                           # the same samples: the fit would not change
        xs = x[sub]
        if xs.max() - xs.min() >= 0.1 * (n - 1):
            slope, icpt = np.polyfit(xs, z[sub], 1)
            new = icpt + slope * x
        else:                               # too short a stretch to trust a tilt
            new = np.full(n, median(z[sub]))
        done = np.array_equal(sub, substrate)
        base, substrate = new, sub
        if done:
            break
    noise = _robust_std(z[substrate] - base[substrate]) if substrate.sum() >= 3 else 0.0
    return base, noise


def substrate_through(points, length: float) -> tuple[float, float, float] | None:
    """The substrate along a line ``length`` nm long from what other lines measured on it:
    ``points`` of (nm from its start, substrate height, noise); the straight line through
    them (flat through one) as :func:`find_edges` takes ``substrate``; None without any."""
    if not points:
        return None
    s, z, noise = (np.asarray(v, float) for v in zip(*points, strict=True))
    slope = float(np.polyfit(s, z, 1)[0]) if np.ptp(s) >= 1.0 else 0.0
    z0 = float(np.mean(z - slope * s))
    return z0, z0 + slope * length, float(np.mean(noise))
