"""The simulator's creep of many moves in time independent of how many there were.

The creep of moves ``s_i`` completed at ``t_i`` is ``c Σ s_i log10(1 + max(t - t_i, 0) / τ)``
(:class:`~nanoasm.world.sim.drift_model.DriftModel`). Summed directly, every query costs
one term per move ever made: a run of a thousand objects records thousands of moves and
queries the creep for every streamed chunk and scan line.

:class:`CreepSum` folds the moves older than a window into a power series about a time
``t0``. With ``T_i = τ + t0 - t_i`` and ``h = t - t0``,

    Σ s_i log10(1 + (t - t_i) / τ) = C0 + Σ_i s_i log10(1 + h / T_i)
                                  = C0 + Σ_{k≥1} x^k (-1)^(k+1) / (k ln 10) Σ_i s_i (R / T_i)^k,

``C0`` the folded moves' creep at ``t0``, ``R = min T_i`` and ``x = h / R``. This is exact
(no move is forgotten or frozen); for ``|x| <= 1/4`` the series, cut after
:data:`TERMS` terms, leaves less than ``4^-(TERMS+1)`` of ``Σ |s_i|`` (about 1e-16 of it:
float rounding). Fold times lie on a grid (:data:`GRID` s): the queries of one step share
a fold and cost ``TERMS`` terms plus one per move of the window; the next step folds
again, in one pass over the moves, amortised over the queries of that step. Fewer than
:data:`MIN_FOLD` moves old enough are never folded: such sums are made directly, in
blocks of 256 in time order, exactly as before (short runs give the same numbers to the
last bit; the golden dry-runs of the bowtie make up to 2135 moves).
"""

from __future__ import annotations

import math

import numpy as np

#: Terms of the power series (its remainder is below ``RATIO^(TERMS+1)`` of the steps).
TERMS = 24
#: Largest ``|t - t0| / R`` at which the fold is used.
RATIO = 0.25
#: Moves completed within this many seconds before a fold's time stay in the direct sum.
WINDOW = 100.0
#: Step (s) of the grid of fold times: queries within one step share a fold.
GRID = RATIO * WINDOW / 2
#: Fewest moves worth folding: with fewer, the sum is direct (and bit-identical to it).
MIN_FOLD = 4096
_BLOCK = 256  # moves per block of the direct sum (bounded memory)


class CreepSum:
    """``Σ s_i log10(1 + max(t - t_i, 0) / τ)`` over the recorded moves, at many times."""

    def __init__(self, tau: float):
        self.tau = float(tau)
        self._t = np.zeros(0)
        self._s = np.zeros((0, 2))
        self._n = 0
        self._latest = np.zeros(0)     # running maximum of the move times
        self._fold: tuple | None = None  # (key, (moves folded, t0, R, C0 (2,), coefficients (TERMS, 2)))
        self.folds = 0                  # folds made (a measure of cost)

    def __len__(self) -> int:
        return self._n

    def add(self, t: float, step: tuple[float, float]) -> None:
        """Record a move by ``step`` (nm) completed at ``t`` (s)."""
        if self._n == self._t.size:     # grow by doubling: amortised O(1)
            size = max(2 * self._n, 64)
            self._t = np.resize(self._t, size)
            self._s = np.resize(self._s, (size, 2))
            self._latest = np.resize(self._latest, size)
        self._t[self._n] = t
        self._s[self._n] = step
        self._latest[self._n] = t if self._n == 0 else max(t, self._latest[self._n - 1])
        self._n += 1

    def __call__(self, t: np.ndarray) -> np.ndarray:
        """``(n, 2)``: the sums at times ``t`` ``(n,)`` (s)."""
        t = np.asarray(t, float).reshape(-1)
        acc = np.zeros((t.size, 2))
        if self._n == 0 or t.size == 0:
            return acc
        fold = self._fold_for(float(t.min()), float(t.max()))
        start = 0
        if fold is not None:
            start, t0, R, c0, coef = fold
            x = (t - t0) / R
            poly = np.zeros((t.size, 2))
            for k in range(TERMS - 1, -1, -1):     # Horner: Σ_k x^(k+1) coef[k]
                poly = (poly + coef[k]) * x[:, None]
            acc += c0 + poly
        ts, ss = self._t[:self._n], self._s[:self._n]
        for i in range(start, self._n, _BLOCK):
            dt = np.maximum(t[:, None] - ts[None, i:i + _BLOCK], 0.0)
            acc += np.log10(1.0 + dt / self.tau) @ ss[i:i + _BLOCK]
        return acc

    def _fold_for(self, lo: float, hi: float) -> tuple | None:
        """The fold for every time in ``[lo, hi]``, or None when too few moves are old
        enough to fold. Its time ``t0`` lies on a grid of step ``GRID 2^k`` (the least
        ``k`` whose step covers ``hi - lo``) and it folds the moves that ended
        ``WINDOW 2^k`` s before ``t0 + τ``: a function of the moves and the query alone,
        whatever was asked before (a restored simulator sums as the one it was saved from)."""
        k = 0
        while GRID * 2.0**k < hi - lo:
            k += 1
        step, need = GRID * 2.0**k, WINDOW * 2.0**k          # [lo, hi] within [t0, t0 + RATIO need)
        t0, tau = math.floor(lo / step) * step, self.tau
        n = int(np.searchsorted(self._latest[:self._n], t0 + tau - need, side="right"))
        if n < MIN_FOLD:
            return None
        key = (k, t0, n)
        if self._fold is not None and self._fold[0] == key:
            return self._fold[1]
        ts, ss = self._t[:n], self._s[:n]
        T = tau + t0 - ts                                     # >= need
        R = float(T.min())
        c0 = np.zeros(2)
        for i in range(0, n, _BLOCK):
            c0 += np.log10(1.0 + (t0 - ts[i:i + _BLOCK]) / tau) @ ss[i:i + _BLOCK]
        m = np.arange(1, TERMS + 1)
        powers = (R / T)[None, :] ** m[:, None]               # (TERMS, n)
        coef = ((-1.0) ** (m + 1) / (m * math.log(10.0)))[:, None] * (powers @ ss)
        self._fold = (key, (n, t0, R, c0, coef))
        self.folds += 1
        return self._fold[1]
