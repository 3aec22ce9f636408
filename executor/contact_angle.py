"""Where a pushed object sits on the tip, from the forces the lever measures (issue 13).

While the tip pushes, the object's contact force acts along the tip–object contact
normal; the tip–substrate friction acts against the motion. The angle α from the tip's
motion to that normal (counter-clockwise, the object to the left of the tip's line for
α > 0) puts the object's centre at ``r_c sin α`` across the line, ``r_c`` the contact
distance (object radius plus tip radius).

The forces come from the compensated signals (eq. 3.28) by eq. 3.5, 3.6 and 3.9 in the
cantilever frame: ``F_y = (k_l K_l / h) S̄_l`` and, with F_z unchanged, ``F_x = (l / h)
k K_n ΔS̄_n``; eq. 3.12 (``R(ψ)⁻¹``) takes them to the AFM frame. Eq. 3.11 closes the
system by assuming the force opposes the motion, which is what this estimate must not
assume; F_z is instead eliminated by a reference: the samples where the tip slides in
contact before it meets the object (the push is put down ``lead`` nm short of contact),
whose force is friction alone, along the motion. The change from that reference to a
window of the push is the contact force, less the change of friction on the excess
load (``μ_ts F̄_z``, along the motion: it shortens the along-line part, so |α| reads a
little large, never on the wrong side).

Without calibrated baseline maps the lateral baseline is one number from free air,
but the piezo's bow tilts it along the scanner's x (eq. 3.28's B(i, j), seed Fig. 3.14):
over a 400 nm push along x on a 4 µm area that tilt reads as 2°. :func:`baseline_slope`
measures it from the lifted travel before the push (S̄_l against x, the tip at one
height) and :func:`contact_angle` removes it.

Its uncertainty follows from the scatter of the samples in both windows (noise, and
the object's own jitter); ``l / h`` (about 67 for the seed's lever) makes S̄_n the
noisier channel, so a push along the cantilever's X axis measures α through S̄_l, far
better than one along its Y axis measures it through S̄_n.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nanoasm.world.cantilever import Cantilever, to_afm

#: Least contact force (nN) for an angle: below it the tip is not against the object.
MIN_FORCE = 2.0


@dataclass(frozen=True)
class ContactAngle:
    """``angle`` (deg, from the motion to the contact normal, counter-clockwise), its 1σ
    ``std`` (deg) and the contact force's size ``force`` (nN) over the window."""

    angle: float
    std: float
    force: float

    def lateral(self, contact_distance: float) -> tuple[float, float]:
        """The object's centre across the tip's line (nm, + to the left) and its 1σ."""
        a = math.radians(self.angle)
        return contact_distance * math.sin(a), contact_distance * math.cos(a) * math.radians(self.std)


def _mean_std(x: np.ndarray) -> tuple[float, float]:
    """The mean of at least two samples and its standard error: ``x.mean()`` and
    ``x.std(ddof=1)``'s values, summed as numpy sums them (one sum for both, without
    their dispatch)."""
    n = x.size
    mean = np.add.reduce(x) / n
    d = x - mean
    return float(mean), math.sqrt(float(np.add.reduce(d * d) / (n - 1))) / math.sqrt(n)


def _gains(lever: Cantilever) -> tuple[float, float]:
    """nN per volt of S̄_n change (F_x at constant F_z, eq. 3.6) and of S̄_l (F_y, eq. 3.9)."""
    return lever.lever_length / lever.tip_height * lever.spring_constant * lever.normal_gain, lever.lateral_gain


#: Least spread (nm) of scanner x over which the lateral baseline's slope is fitted.
MIN_SPREAD = 200.0


#: Lifted samples farther than this (nm, along x) from the push do not fit its baseline's slope.
SLOPE_REACH = 1000.0


def baseline_slope(x: np.ndarray, sl_bar: np.ndarray, around: tuple[float, float] | None = None) -> float:
    """The lateral baseline's slope (V/nm along scanner x) from lifted samples at one
    height, those within :data:`SLOPE_REACH` of the x range ``around`` (the push's) if
    given: a least-squares line; 0 when their x spans less than :data:`MIN_SPREAD`."""
    x, sl_bar = np.asarray(x, float), np.asarray(sl_bar, float)
    if around is not None:
        near = _near(x, around)
        x, sl_bar = x[near], sl_bar[near]
    if x.size < 3 or float(np.ptp(x)) < MIN_SPREAD:
        return 0.0
    return float(np.polyfit(x, sl_bar, 1)[0])


def _near(x: np.ndarray, around: tuple[float, float]) -> np.ndarray:
    """Which of ``x`` lie within :data:`SLOPE_REACH` of the range ``around``."""
    return (x >= around[0] - SLOPE_REACH) & (x <= around[1] + SLOPE_REACH)


def contact_angle(sn_bar: np.ndarray, sl_bar: np.ndarray, reference: np.ndarray, window: np.ndarray,
                  motion, psi: float, lever: Cantilever, x: np.ndarray | None = None,
                  slope: float = 0.0) -> ContactAngle | None:
    """α from compensated signals ``sn_bar``, ``sl_bar`` (V) of one push: ``reference``
    and ``window`` index the samples sliding before contact and those to measure;
    ``motion`` is the tip's direction over the window (AFM frame), ``psi`` the scan angle
    (deg); ``x`` the samples' scanner x (nm) with the lateral baseline's ``slope`` (V/nm,
    :func:`baseline_slope`). None when either window is empty or the contact force is
    below :data:`MIN_FORCE` (the tip is not against an object)."""
    if len(reference) < 2 or len(window) < 2:
        return None
    if slope and x is not None:
        sl_bar = np.asarray(sl_bar, float) - slope * np.asarray(x, float)
    m = np.asarray(motion, float)
    m = m / np.linalg.norm(m)
    ref_n, ref_n_s = _mean_std(sn_bar[reference])
    ref_l, ref_l_s = _mean_std(sl_bar[reference])
    win_n, win_n_s = _mean_std(sn_bar[window])
    win_l, win_l_s = _mean_std(sl_bar[window])
    gx, gy = _gains(lever)
    fx, fy = gx * (win_n - ref_n), gy * (win_l - ref_l)
    sx, sy = gx * math.hypot(win_n_s, ref_n_s), gy * math.hypot(win_l_s, ref_l_s)
    f = to_afm(np.array([fx, fy]), psi)
    a, c = float(f @ m), float(f @ np.array([-m[1], m[0]]))   # the force on the tip: along, across
    size = math.hypot(a, c)
    if size < MIN_FORCE:
        return None
    # the force on the tip is minus the contact normal: α = atan2(-c, -a); its 1σ is the
    # force's error across its own direction over its size
    rot = to_afm(np.eye(2), psi)                    # rows: the cantilever x and y in the AFM frame
    cov = rot.T @ np.diag([sx * sx, sy * sy]) @ rot
    normal = np.array([-f[1], f[0]]) / size
    return ContactAngle(math.degrees(math.atan2(-c, -a)), math.degrees(math.sqrt(float(normal @ cov @ normal)) / size),
                        size)


#: Length (nm) of the push's end over which the angle is measured.
WINDOW = 30.0
#: Share of the lead (the tip's slide before contact) taken as the friction reference.
REFERENCE_SHARE = 0.6
#: Length (nm) after touch-down that sets the level the contact force's onset is told from,
#: the length the force is smoothed over to find it, and the least reference left.
SETTLE, SMOOTH, MIN_REFERENCE = 3.0, 4.0, 4.0


def _onset(sn: np.ndarray, sl: np.ndarray, along: np.ndarray, lever: Cantilever, within: float = math.inf) -> float:
    """Where (nm along the push) the contact force first rises above its level over the
    first :data:`SETTLE` nm by 5σ of the smoothed noise (at least :data:`MIN_FORCE`): the
    object met earlier than the plan put it (its place along the push is known worst).
    Looked for ``within`` nm of the start only (inf if it is not there): the force is
    smoothed over the samples up to there and the smoothing's reach beyond."""
    return _onset_over(sn, sl, along, lever, within, *_onset_reach(along, within))


def _onset_reach(along: np.ndarray, within: float) -> tuple[int, int, int]:
    """What :func:`_onset` reads of samples at ``along``: the first ``n_first`` set its
    level, it smooths over ``k`` samples, and it reads the first ``cut``."""
    n_first = int(np.searchsorted(along, SETTLE, side="right"))     # along never falls
    if n_first < 5:
        n_first = min(5, along.size)
    per_nm = along.size / max(float(along[-1]), 1e-9)
    k = max(1, int(round(SMOOTH * per_nm)))
    cut = max(min(int(np.searchsorted(along, within, side="right")) + k, along.size), n_first)
    return n_first, k, cut


def _onset_over(sn: np.ndarray, sl: np.ndarray, along: np.ndarray, lever: Cantilever, within: float,
                n_first: int, k: int, cut: int) -> float:
    """:func:`_onset` given its :func:`_onset_reach`."""
    gx, gy = _gains(lever)
    first = np.arange(n_first)
    sn, sl, along = sn[:cut], sl[:cut], along[:cut]
    fx, fy = gx * (sn - sn[first].mean()), gy * (sl - sl[first].mean())
    kernel = np.ones(k) / k
    mag = np.hypot(np.convolve(fx, kernel, mode="same"), np.convolve(fy, kernel, mode="same"))
    noise = math.hypot(float(fx[first].std()), float(fy[first].std())) / math.sqrt(k)
    above = np.flatnonzero((mag > max(MIN_FORCE, 5.0 * noise)) & (along > SETTLE) & (along <= within))
    return float(along[above[0]]) if above.size else math.inf


class PushSignals:
    """The signals of one streamed push, kept chunk by chunk, and the angle at its end
    (:meth:`angle`): the reference is the first ``REFERENCE_SHARE × lead`` nm of sliding
    after touch-down, cut short where the contact force rises if the object was met
    sooner (at least :data:`MIN_REFERENCE` nm, else no angle); the window is the last
    :data:`WINDOW` nm in contact.

    A tracked push reads the angle after every chunk of a hundred samples. Given a
    ``key`` that changes whenever ``compensate`` would (the monitor's free-air baselines),
    :meth:`angle` compensates each chunk once and keeps the samples in contact and their
    distance along the push as they grow, instead of all of them again each time (a push
    of n samples cost n²/100); it reads only the samples its windows take. The values
    are those of the whole computation (``key`` None), which a test checks."""

    def __init__(self, lead: float):
        self.lead = float(lead)
        self.push: list[tuple[np.ndarray, ...]] = []      # (S_n, S_l, x, y) of push samples
        self.lifted: list[tuple[np.ndarray, ...]] = []    # the same of lifted travel
        self._kept: _Contact | None = None                # the samples in contact, compensated, for a key
        self._slope: list | None = None                   # the lifted samples compensated, for a key

    def add(self, s_n, s_l, xy, pushing: np.ndarray, lifted: np.ndarray) -> None:
        """One chunk: raw signals, scanner ``xy`` ``(n, 2)`` nm, and which samples push
        and which travel lifted."""
        for keep, mask in ((self.push, pushing), (self.lifted, lifted)):
            if mask.any():
                keep.append((s_n[mask], s_l[mask], xy[mask, 0], xy[mask, 1]))

    def angle(self, compensate, level: float, motion, psi: float, lever: Cantilever,
              key=None) -> ContactAngle | None:
        """α at the push's end from the samples in contact (compensated S̄_n at least half
        the preload's ``level``); ``compensate(s_n, s_l, xy)`` gives (S̄_n, S̄_l) (eq.
        3.28, the push monitor's), the same for as long as ``key`` is (None: compensate
        every sample anew). None without enough samples or contact force."""
        if not self.push:
            return None
        if key is None:                 # every sample at once
            kept = _Contact(None)
            kept.add(*_in_contact(compensate, level, *(np.concatenate(c) for c in zip(*self.push))))
        else:                           # the chunks since the last read
            kept = self._kept
            if kept is None or kept.key != (key, level):
                kept = self._kept = _Contact((key, level))
            for chunk in self.push[kept.chunks:]:
                kept.add(*_in_contact(compensate, level, *chunk))
            kept.chunks = len(self.push)
        sn, sl, x, along = kept.view()
        if x.size < 2:
            return None
        if along[-1] < self.lead + WINDOW:           # too short to have both apart
            return None
        share = REFERENCE_SHARE * self.lead                 # an onset beyond share + SETTLE does not matter
        end = min(share, kept.onset(sn, sl, along, lever, share + SETTLE) - SETTLE)
        if end < MIN_REFERENCE:
            return None
        reference = np.arange(int(np.searchsorted(along, end, side="right")))          # along never falls
        window = np.arange(int(np.searchsorted(along, along[-1] - WINDOW, side="left")), along.size)
        slope = self._lifted_slope(compensate, key, kept.span) if self.lifted else 0.0
        take = np.concatenate([reference, window])          # the samples the two windows read, alone
        return contact_angle(sn[take], sl[take], np.arange(reference.size), np.arange(reference.size, take.size),
                             motion, psi, lever, x[take], slope)

    def _lifted_slope(self, compensate, key, span) -> float:
        """:func:`baseline_slope` of the lifted samples about the contact's x ``span``,
        compensated once for a ``key``, and fitted again only when other samples lie near
        the span."""
        got = self._slope
        if key is None or got is None or got[0] != (key, len(self.lifted)):
            ln, ll, lx, ly = (np.concatenate(c) for c in zip(*self.lifted))
            got = [(key, len(self.lifted)), lx, compensate(ln, ll, np.column_stack([lx, ly]))[1], None]
            if key is not None:
                self._slope = got
        if span is None:
            return baseline_slope(got[1], got[2])
        near = _near(got[1], span)
        if got[3] is None or not np.array_equal(got[3][0], near):      # the same samples: the same fit
            got[3] = (near, baseline_slope(got[1][near], got[2][near]))
        return got[3][1]


def _in_contact(compensate, level: float, s_n, s_l, x, y) -> tuple[np.ndarray, ...]:
    """Compensated (S̄_n, S̄_l, x, y) of the samples whose S̄_n is at least half ``level``."""
    sn, sl = compensate(s_n, s_l, np.column_stack([x, y]))
    down = sn >= 0.5 * level
    return sn[down], sl[down], x[down], y[down]


class _Contact:
    """The samples in contact of a push as they come, and their distance along it
    (nm, from the first), in arrays that grow by doubling: ``np.cumsum`` continued from
    the last distance adds in the order it adds over the whole."""

    def __init__(self, key):
        self.key, self.chunks, self.n = key, 0, 0
        self.arrays = [np.empty(0) for _ in range(5)]        # S̄_n, S̄_l, x, y, along
        self.span: tuple[float, float] | None = None
        self._onset: tuple | None = None                    # (what it read, the onset)

    def add(self, sn, sl, x, y) -> None:
        if not x.size:
            return
        if self.n:
            last = self.n - 1
            steps = np.hypot(np.diff(x, prepend=self.arrays[2][last]), np.diff(y, prepend=self.arrays[3][last]))
            along = np.cumsum(np.concatenate([[self.arrays[4][last]], steps]))[1:]
        else:
            along = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
        lo, hi = float(x.min()), float(x.max())
        self.span = (lo, hi) if self.span is None else (min(self.span[0], lo), max(self.span[1], hi))
        end = self.n + x.size
        if end > self.arrays[0].size:
            size = max(2 * self.arrays[0].size, end, 1024)
            self.arrays = [np.concatenate([a[:self.n], np.empty(size - self.n)]) for a in self.arrays]
        for a, v in zip(self.arrays, (sn, sl, x, y, along)):
            a[self.n:end] = v
        self.n = end

    def onset(self, sn, sl, along, lever: Cantilever, within: float) -> float:
        """:func:`_onset` of the samples so far (:meth:`view`), kept while what it reads stays
        the same: the samples only grow, so the same reach reads the same values."""
        reach = _onset_reach(along, within)
        if self._onset is None or self._onset[0] != (reach, within, lever):
            self._onset = ((reach, within, lever), _onset_over(sn, sl, along, lever, within, *reach))
        return self._onset[1]

    def view(self) -> tuple[np.ndarray, ...]:
        """(S̄_n, S̄_l, x, along) so far (views)."""
        sn, sl, x, _, along = (a[:self.n] for a in self.arrays)
        return sn, sl, x, along
