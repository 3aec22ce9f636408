"""Edges of one object on one AFM scan line.

A local scan line is a height profile: ``n`` samples, equally spaced, along a segment
of length ``length`` from its start ``a``. An object on the line shows as a bump on the
substrate; where the bump crosses a level at ``fraction`` of the object's expected
height above the substrate are its two edges (the seed's P1, P2 or Q1, Q2, ch. 5).

The tip broadens an object by the same amount on both sides, so the midpoint of the two
crossings is the object's centre along the line whatever the tip, and the level set of
the image of a disc or capsule is again a disc or capsule (of a larger radius): a chord
of it is bisected by the object's axis when it crosses the axis at a right angle.

The substrate is a straight line (a tilted sample) fitted to the samples that lie well
below the object, found by iterating from a low quantile (:mod:`.substrate`); the noise
is the robust spread of the substrate samples about it. Crossings are interpolated inversely (position as a
function of height) through the two samples that bracket the level and the next one
into the object: at 1 nm sampling this is within 0.05 nm of the exact crossing on the
flank of a sphere seen by a spherical tip, which turns vertical just below half height,
and exact on the straight flank that a conical tip draws.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nanoasm.param import number

from .substrate import _check_profile, fit_baseline

#: Largest height magnitude accepted in a profile (nm); larger is not a height.
MAX_HEIGHT = 1e9
#: A bump that dips between two summits by more than this fraction of the object's
#: height is two objects touching (a single sphere or rod image has one summit or a
#: flat top); their inner edges are not seen, so it gives no crossing pair.
MERGE_DIP = 0.15
#: The reason given for such a bump.
TOUCHING = "two objects touch on the line"
#: A bump higher than this share of the expected height (plus three noise) is another
#: object, never the one looked for (identification measures heights to about 1 %).
TALLER = 1.2
#: The reason given when every bump on the line is such an object.
TALLER_ONLY = "only taller objects on the line"


@dataclass(frozen=True)
class Edges:
    """The two crossings of one object on a scan line, or why there are none.

    Attributes
    ----------
    found : bool
    reason : str
        ``"found"``; ``"nothing above the level"``; ``"object cut by the line end"``
        (something crosses the level but runs off the line, so one edge is unseen);
        ``"two objects touch on the line"`` (the nearest bump has two summits).
    left, right : float or None
        Crossing positions, nm from the line's start, ``0 < left < right < length``.
    left_std, right_std : float or None
        Their 1-σ precision (nm) from the noise, the edge slope and the sampling.
    peak : float or None
        Largest height of the object above the substrate (nm).
    level : float
        The crossing level above the substrate (nm).
    noise : float
        Estimated (or given) height noise rms of the profile (nm).
    candidates : int
        Number of separate bumps that crossed the level (the nearest to the expected
        position was taken).
    end : (position, 1-σ, side) or None
        When no crossing pair was found because the object's bump runs off the line or
        into a touching neighbour: its one clear crossing (nm from the line's start), its
        1-σ, and on which side of the object it lies (-1 toward the line's start, +1 its
        end). A rod whose end touches a particle keeps its other end (see
        :mod:`~.rod_scan`).
    substrate : float or None
        Where found: the substrate's height under the object's centre (nm, the profile's
        heights), which a line that sees no substrate of its own can be given.
    inner : (left, right, left_std, right_std, level) or None
        When no crossing pair was found because neighbours on both sides touch the object
        (their tip-broadened images meet its image above the crossing level, as at the
        ends of a rod between two particles): its crossings at ``level``, halfway between
        the higher of the two saddles and its summit. Symmetric about the object's centre
        for a symmetric object; its chord is shorter than at the usual level.
    """

    found: bool
    reason: str
    left: float | None
    right: float | None
    left_std: float | None
    right_std: float | None
    peak: float | None
    level: float
    noise: float
    candidates: int
    end: tuple[float, float, int] | None = None
    substrate: float | None = None
    inner: tuple[float, float, float, float, float] | None = None

    @property
    def centre(self) -> float | None:
        """Midpoint of the two crossings (nm from the line's start)."""
        return None if not self.found else 0.5 * (self.left + self.right)

    @property
    def centre_std(self) -> float | None:
        return None if not self.found else 0.5 * math.hypot(self.left_std, self.right_std)

    @property
    def width(self) -> float | None:
        """Chord between the two crossings (nm)."""
        return None if not self.found else self.right - self.left

    @property
    def width_std(self) -> float | None:
        return None if not self.found else math.hypot(self.left_std, self.right_std)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Inclusive index ranges ``(i, j)`` of the True runs of ``mask``."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    starts = np.nonzero(d == 1)[0]
    ends = np.nonzero(d == -1)[0] - 1
    return list(zip(starts.tolist(), ends.tolist(), strict=True))


def _merge(runs: list[tuple[int, int]], y: np.ndarray, floor: float) -> list[tuple[int, int]]:
    """Join neighbouring runs whose gap never drops below ``floor`` (a noise dip)."""
    out: list[tuple[int, int]] = []
    for i, j in runs:
        if out and y[out[-1][1] + 1:i].min() > floor:
            out[-1] = (out[-1][0], j)
        else:
            out.append((i, j))
    return out


def _dips(y: np.ndarray) -> np.ndarray:
    """Each sample's drop below the lower of the highest values on its either side."""
    left = np.maximum.accumulate(y)
    right = np.maximum.accumulate(y[::-1])[::-1]
    return np.minimum(left, right) - y


def _clear_end(y: np.ndarray, run: tuple[int, int], expected: float, level: float, h: float,
               noise: float, dip_limit: float) -> tuple[float, float, int] | None:
    """The one crossing of the bump ``run`` that belongs to the object at ``expected``
    alone (see :attr:`Edges.end`): where the bump runs off one end of the line, its
    other crossing; where it holds two summits (a touching neighbour), the crossing on
    the side of ``expected`` away from the dip between them. None when neither holds."""
    i, j = run
    n = y.size
    dips = _dips(y[i:j + 1])
    if i > 0 and j < n - 1:
        if dips.max() <= dip_limit:
            return None
        side = -1 if expected < (i + int(np.argmax(dips))) * h else 1
    elif i > 0:
        side = -1
    elif j < n - 1:
        side = 1
    else:
        return None
    at, std = _crossing(y, i - 1, i, level, h, noise) if side < 0 else _crossing(y, j + 1, j, level, h, noise)
    return float(at), float(std), side


def _valley_floor(seg: np.ndarray, deep: np.ndarray, at: int, step: int) -> int:
    """The lowest sample of the run of ``deep`` samples that ``at`` ends (walking ``step``)."""
    stop = at
    while 0 <= stop + step < seg.size and deep[stop + step]:
        stop += step
    lo, hi = sorted((at, stop))
    return lo + int(np.argmin(seg[lo:hi + 1]))


def _between_saddles(y: np.ndarray, run: tuple[int, int], expected: float, h: float, noise: float,
                     dip_limit: float) -> tuple[float, float, float, float, float] | None:
    """The crossings of the object at ``expected`` within the bump ``run`` between the
    nearest saddle deeper than ``dip_limit`` on either side of it (see
    :attr:`Edges.inner`; the deepest point of that valley), or None where a side has none."""
    i, j = run
    seg = y[i:j + 1]
    if seg.size < 3:
        return None
    k = min(max(round(expected / h) - i, 1), seg.size - 2)
    deep = _dips(seg) > dip_limit
    before, after = np.nonzero(deep[:k])[0], k + 1 + np.nonzero(deep[k + 1:])[0]
    if not before.size or not after.size:
        return None
    a, b = _valley_floor(seg, deep, int(before[-1]), -1), _valley_floor(seg, deep, int(after[0]), 1)
    peak = float(seg[a:b + 1].max())
    level = max(seg[a], seg[b]) + 0.5 * (peak - max(seg[a], seg[b]))
    top = a + int(np.argmax(seg[a:b + 1]))
    lo = a + int(np.nonzero(seg[a:top + 1] <= level)[0][-1])      # last sample below, left of the summit
    hi = top + int(np.nonzero(seg[top:b + 1] <= level)[0][0])       # first one below, right of it
    left, left_std = _crossing(y, i + lo, i + lo + 1, level, h, noise)
    right, right_std = _crossing(y, i + hi, i + hi - 1, level, h, noise)
    if not left < right:
        return None
    return float(left), float(right), float(left_std), float(right_std), float(level)


def _crossing(y: np.ndarray, lo: int, hi: int, level: float, h: float,
              noise: float) -> tuple[float, float]:
    """Crossing between samples ``lo`` and ``hi = lo ± 1`` (``y[hi] > level >= y[lo]``).

    Inverse quadratic interpolation: the position as a quadratic function of the height
    through the bracket and the next sample into the object, which follows a flank that
    turns steep (a spherical tip near a particle's equator) where interpolating the
    height would not; linear between the bracket when that sample does not rise further
    above the noise. Returns the position (nm from sample 0) and its 1-σ: the noise over
    the slope; the sampling, when one sample spans much of the level; and the change
    that the quadratic made to the linear estimate (or, for the linear one, its bound
    ``w(1-w) h² |y''| / 2`` over the slope).
    """
    n = y.size
    y0, y1 = y[lo], y[hi]
    rise = y1 - y0                           # > 0 by the bracket
    w = (level - y0) / rise                  # in [0, 1)
    linear = lo + w * (hi - lo)
    sig_noise = noise * math.sqrt(w * w + (1 - w) ** 2) / (rise / h)
    # a flank that jumps a good part of the level in one sample is not resolved: the
    # crossing may be anywhere between the samples (h / sqrt(12) when it jumps it all)
    sig_noise = math.hypot(sig_noise, h / math.sqrt(12) * min(1.0, rise / level) ** 2)
    k = 2 * hi - lo
    if 0 <= k < n and y[k] - y1 > max(3 * noise, 1e-9 * abs(rise)):
        y2 = y[k]
        t0 = (level - y1) * (level - y2) / ((y0 - y1) * (y0 - y2))
        t1 = (level - y0) * (level - y2) / ((y1 - y0) * (y1 - y2))
        t2 = (level - y0) * (level - y1) / ((y2 - y0) * (y2 - y1))
        quad = lo * t0 + hi * t1 + k * t2
        if min(lo, hi) <= quad <= max(lo, hi):
            return quad * h, math.hypot(sig_noise, abs(quad - linear) * h)
    i = min(lo, hi)
    second = [y[j - 1] - 2 * y[j] + y[j + 1] for j in (i, i + 1) if 0 < j < n - 1]
    curv = max((abs(v) for v in second), default=0.0)
    sig_interp = w * (1 - w) * curv / (2 * rise) * h
    return linear * h, math.hypot(sig_noise, sig_interp)


def find_edges(profile, length: float, height: float, *, fraction: float = 0.5,
               expected: float | None = None, noise_rms: float | None = None,
               taller: float | None = TALLER, substrate: tuple[float, float, float] | None = None) -> Edges:
    """The two crossings of an object of expected ``height`` on a scan line.

    Parameters
    ----------
    profile : (n,) array
        Heights in nm at ``n >= 5`` equally spaced samples from the line's start to
        its end (both included); finite.
    length : float
        Length of the line (nm).
    height : float
        Expected height of the object above the substrate (nm): the diameter of a
        particle or of a rod.
    fraction : float
        The crossing level as a fraction of ``height``, in (0, 1); half height by
        default, where the flanks of a tip-broadened sphere or cylinder are steepest.
    expected : float, optional
        Where the object is expected (nm from the start); the centre by default. Of
        several bumps, the one whose crossing interval is nearest to it is taken (one
        that contains it is at distance 0).
    noise_rms : float, optional
        Height noise (nm); estimated from the substrate samples when not given.
    taller : float, optional
        A bump whose summit is higher than ``taller * height`` plus three noise is
        another object (a taller neighbour the line runs into) and is never taken; None
        takes any bump.
    substrate : (start, end, noise), optional
        The substrate as other lines measured it: its height at the line's start and end
        (nm, linear between) and the noise about it. Where the profile's own substrate
        line lies more than the substrate band from it at ``expected``, the line saw no
        substrate of its own (a rod's axis line whose ends both lie on particles beside
        the rod: the dips between them, broadened by the tip, never reach it), and the
        substrate is fitted from ``substrate`` instead (which, with its noise, stands
        where no sample lies within the band of it).

    Returns
    -------
    Edges
        Never raises for a finite profile; ``found`` is False with a ``reason`` when no
        bump has both crossings on the line.
    """
    z = _check_profile(profile)
    length = number("length", length, positive=True)
    height = number("height", height, positive=True)
    if not 0 < fraction < 1:
        raise ValueError(f"fraction must be in (0, 1), got {fraction}")
    expected = 0.5 * length if expected is None else number("expected", expected)
    if noise_rms is not None:
        number("noise_rms", noise_rms, nonnegative=True)
    n = z.size
    h = length / (n - 1)
    band = min(0.15, 0.5 * fraction)
    base, est = fit_baseline(z, h, height, band=band)
    if substrate is not None:
        given = np.linspace(float(substrate[0]), float(substrate[1]), n)
        k = min(max(round(expected / h), 0), n - 1)
        if abs(base[k] - given[k]) > band * height:
            base, est = fit_baseline(z, h, height, band=band, start=given)
            est = est or float(substrate[2])
    noise = est if noise_rms is None else float(noise_rms)
    y = z - base
    level = fraction * height
    runs = _merge(_runs(y > level), y, level - 4 * noise)

    def distance(run: tuple[int, int]) -> tuple[float, float]:
        s1, s2 = (run[0] - 0.5) * h, (run[1] + 0.5) * h
        return max(s1 - expected, expected - s2, 0.0), abs(0.5 * (s1 + s2) - expected)

    dip_limit = max(MERGE_DIP * height, 8 * noise)

    def miss(reason: str, count: int, end: bool = False) -> Edges:
        run = min(runs, key=distance) if end else None
        inner = _between_saddles(y, run, expected, h, noise, dip_limit) if end else None
        one = _clear_end(y, run, expected, level, h, noise, dip_limit) if end and inner is None else None
        return Edges(False, reason, None, None, None, None, None, level, noise, count, one, None, inner)

    if not runs:
        return miss("nothing above the level", 0)
    inner = [(i, j) for i, j in runs if i > 0 and j < n - 1]
    if not inner:
        return miss("object cut by the line end", len(runs), end=True)
    if taller is not None:
        cap = taller * height + 3 * noise
        inner = [(i, j) for i, j in inner if y[i:j + 1].max() <= cap]
        if not inner:
            return miss(TALLER_ONLY, len(runs), end=True)
    i, j = min(inner, key=distance)
    if float(_dips(y[i:j + 1]).max()) > dip_limit:
        return miss(TOUCHING, len(runs), end=True)
    left, left_std = _crossing(y, i - 1, i, level, h, noise)
    right, right_std = _crossing(y, j + 1, j, level, h, noise)
    peak = float(y[i:j + 1].max())
    return Edges(True, "found", float(left), float(right), float(left_std), float(right_std),
                 peak, level, noise, len(runs), None, float(np.interp(0.5 * (left + right) / h, np.arange(n), base)))
