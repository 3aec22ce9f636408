"""The creep of moves too old to keep one by one, still creeping.

A move ``s_i`` completed at ``t_i`` creeps ``c s_i log10(1 + (t - t_i) / τ)`` for ever: its
rate falls as ``1/t`` but never stops, and over a long run the slow tails of thousands of
moves add up. Freezing each old move's creep into a constant (what
:class:`~nanoasm.drift.creep.CreepHistory` did) dropped those tails: on a 1000-object
scene (``scale1000``, seed 1) the 256 moves kept were a few minutes' worth, and the
estimate fell 6-8 nm further behind the simulated truth in each 60 s survey image (5 to
25 nm over three), while it reported σ 4-7 nm (its references then failed the gate one after
another and a relocalisation followed).

:class:`FrozenMoves` keeps them exactly, in a size independent of their number: the
moves are binned in time, and each bin keeps the moments of its steps about its centre
``c``, ``M_k = Σ s_i (t_i - c)^k``. With ``u = t + τ`` and ``d = u - c``,

    Σ s_i log10(1 + (t - t_i) / τ) = M_0 log10(d / τ) - Σ_{k≥1} M_k / (k ln 10 d^k),

a series in ``(t_i - c) / d``, which a bin's width keeps small: a move goes, when it is
frozen at age ``A``, into a bin no wider than ``A /`` :data:`BIN_AGE`, and bins are merged
into ones twice as wide as they age (the moments moved to the new centre exactly), so
their count grows with the logarithm of the run's length. Cut after :data:`ORDER`
moments, the sum errs by less than ``(1/15)^(ORDER+1)`` of the bin's ``Σ |s_i|``.
"""

from __future__ import annotations

import math

import numpy as np

#: Moments kept per bin, beyond the zeroth.
ORDER = 5
#: Width (s) of the narrowest bins.
BIN0 = 0.25
#: A bin is at most this fraction of the age of the moves it takes (and of its own age
#: when bins merge).
BIN_AGE = 8.0

_K = np.arange(ORDER + 1)
_BINOMIAL = np.array([[math.comb(i, j) for j in range(ORDER + 1)] for i in range(ORDER + 1)], float)
_LOWER = _K[:, None] >= _K[None, :]
_EXPONENT = np.maximum(_K[:, None] - _K[None, :], 0)


class FrozenMoves:
    """``Σ s_i log10(1 + (t - t_i) / τ)`` over moves frozen at least a bin's width ago."""

    def __init__(self, tau: float):
        self.tau = float(tau)
        self.bins: dict[tuple[int, int], np.ndarray] = {}     # (level, index) -> (ORDER + 1, 2) moments
        self.revision = 0                                      # one more at every change of the bins
        self._arrays: tuple | None = None                      # the bins as arrays, at a revision

    def __len__(self) -> int:
        return len(self.bins)

    @property
    def steps(self) -> np.ndarray:
        """(2,): ``Σ s_i`` of every frozen move (the bins' zeroth moments)."""
        return sum((m[0] for m in self.bins.values()), np.zeros(2))

    @staticmethod
    def _centre(level: int, index: int) -> float:
        w = BIN0 * 2.0**level
        return (index + 0.5) * w

    def add(self, now: float, times, steps) -> None:
        """Freeze the moves ``steps`` ((n, 2) nm) completed at ``times`` ((n,) s) at ``now``."""
        times = np.asarray(times, float).reshape(-1)
        steps = np.asarray(steps, float).reshape(-1, 2)
        k = np.arange(ORDER + 1)
        for t, s in zip(times, steps):
            age = max(now - t, 0.0)
            level = max(0, math.floor(math.log2(age / (BIN_AGE * BIN0)))) if age > BIN_AGE * BIN0 else 0
            w = BIN0 * 2.0**level
            key = (level, math.floor(t / w))
            m = self.bins.get(key)
            if m is None:
                m = self.bins[key] = np.zeros((ORDER + 1, 2))
            m += ((t - self._centre(*key)) ** k)[:, None] * s[None, :]
        self.revision += 1
        self._merge(now)

    def _merge(self, now: float) -> None:
        """Merge each bin whose parent (twice as wide) is no wider than its age allows,
        level by level (a parent made may merge on in turn)."""
        levels: dict[int, list] = {}        # each level's keys in the bins' order, parents made appended
        for key in self.bins:
            levels.setdefault(key[0], []).append(key)
        level, top = 0, max(levels, default=-1)
        while level <= top:
            w_parent = BIN0 * 2.0 ** (level + 1)
            for key in levels.get(level, ()):
                parent = (level + 1, key[1] // 2)
                if now - (parent[1] + 1) * w_parent < BIN_AGE * w_parent:
                    continue
                if self._merge_into(key, parent):
                    levels.setdefault(level + 1, []).append(parent)
                    top = max(top, level + 1)
            level += 1

    def _merge_into(self, key: tuple[int, int], parent: tuple[int, int]) -> bool:
        """Bin ``key``'s moments moved to ``parent``'s centre and added there; whether
        ``parent`` is new."""
        # M'_i = Σ_j C(i, j) M_j δ^(i-j), δ the old centre less the new
        delta = self._centre(*key) - self._centre(*parent)
        shifted = (_BINOMIAL * np.where(_LOWER, delta ** _EXPONENT, 0.0)) @ self.bins.pop(key)
        if parent in self.bins:
            self.bins[parent] += shifted
            return False
        self.bins[parent] = shifted
        return True

    def _powers(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``d`` per bin, ``d^-k`` (k = 0..ORDER+1) and the moments, bins in key order (a
        restored set sums alike to the last bit); ``d`` at least the bin's width (a query
        before a bin's moves, which no caller makes, stays finite)."""
        if self._arrays is None or self._arrays[0] != (self.revision, len(self.bins)):
            keys = sorted(self.bins)
            self._arrays = ((self.revision, len(self.bins)),
                            np.array([self._centre(*key) for key in keys], float),
                            np.array([BIN0 * 2.0**key[0] for key in keys], float),
                            np.array([self.bins[key] for key in keys], float).reshape(-1, ORDER + 1, 2))
        _, centres, width, moments = self._arrays
        d = np.maximum(t + self.tau - centres, np.maximum(width, self.tau))
        return d, (1.0 / d)[:, None] ** np.arange(ORDER + 2)[None, :], moments

    def __call__(self, t: float) -> np.ndarray:
        """(2,): the frozen moves' ``Σ s_i log10(1 + (t - t_i) / τ)`` at ``t``."""
        if not self.bins:
            return np.zeros(2)
        d, inv, moments = self._powers(float(t))
        k = np.arange(1, ORDER + 1)
        value = moments[:, 0, :] * np.log10(d / self.tau)[:, None]
        value -= np.einsum("bk,bkj->bj", inv[:, 1:ORDER + 1] / (k * math.log(10.0))[None, :], moments[:, 1:, :])
        return value.sum(axis=0)

    def rate(self, t: float) -> np.ndarray:
        """(2,): the time derivative of :meth:`__call__` at ``t`` (per s)."""
        if not self.bins:
            return np.zeros(2)
        _, inv, moments = self._powers(float(t))
        return np.einsum("bk,bkj->j", inv[:, 1:ORDER + 2], moments) / math.log(10.0)

    def tau_weights(self, t: float) -> np.ndarray:
        """(2,): ``Σ s_i x_i / (1 + x_i)``, ``x_i = (t - t_i) / τ`` (what the creep's
        sensitivity to ``ln τ`` sums): ``Σ s_i - τ Σ s_i / (t + τ - t_i)``."""
        if not self.bins:
            return np.zeros(2)
        _, inv, moments = self._powers(float(t))
        return moments[:, 0, :].sum(axis=0) - self.tau * np.einsum("bk,bkj->j", inv[:, 1:ORDER + 2], moments)

    def state(self) -> dict:
        """JSON types: the bins (level, index, moments)."""
        return {"bins": [[level, index, m.tolist()] for (level, index), m in sorted(self.bins.items())]}

    @classmethod
    def from_state(cls, tau: float, state: dict) -> FrozenMoves:
        out = cls(tau)
        for level, index, m in state.get("bins", []):
            m = np.asarray(m, float)
            if m.shape != (ORDER + 1, 2) or not np.all(np.isfinite(m)):
                raise ValueError(f"a frozen creep bin's moments must be finite, shape ({ORDER + 1}, 2)")
            out.bins[(int(level), int(index))] = m
        out.revision += 1
        return out


__all__ = ["FrozenMoves"]
