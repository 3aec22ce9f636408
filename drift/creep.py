"""Piezo creep after large scanner moves, as a known input to the drift filter.

After a move of the scanner by a step ``s`` (nm vector) completed at ``t_s``, the piezo
keeps extending along the step: ``c s log10(1 + (t - t_s) / τ)``. The tip then sits that
much further along ``s`` than commanded, so the sample appears shifted back: creep adds
``-c s log10(1 + (t - t_s) / τ)`` to the measured offset (the convention of
``nanoasm.world.sim.drift_model``: offset = thermal - creep). The filter subtracts this
input from each measurement and adds it to each predicted offset; its state keeps the
thermal drift alone.

The remaining creep rate of a move, ``c |s| / (ln 10 (τ + t - t_s))``, falls as ``1/t``
but never stops. :class:`CreepHistory` keeps the recent moves one by one and hands a
move whose rate has fallen below ``rate_tol`` (or the oldest, past ``max_moves``) to
:class:`~nanoasm.drift.frozen_creep.FrozenMoves`, which goes on summing its creep
exactly in a size that does not grow with the number of moves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nanoasm.param import param, validate

from .frozen_creep import BIN0, BIN_AGE, FrozenMoves

#: Youngest age (s) at which a move past ``max_moves`` is frozen: a bin then sums it to
#: (1/15)^6 of its step (:mod:`.frozen_creep`); until then it is kept, beyond the count.
FROZEN_AGE = BIN_AGE * BIN0


@dataclass(frozen=True)
class CreepModelParams:
    """Parameters of the creep input.

    Attributes
    ----------
    amplitude : float
        ``c``, fraction of the step per decade of time (``>= 0``; 0 turns creep off).
    tau : float
        ``τ`` in s (``> 0``).
    min_step : float
        Moves shorter than this (nm) add no creep term (``>= 0``).
    rate_tol : float
        A move whose remaining creep rate is below this (nm/s) is frozen (``> 0``).
    max_moves : int
        At most this many moves are kept; the oldest are frozen first (``>= 1``).
    amplitude_std : float
        Standard deviation of ``c`` (per decade, ``>= 0``): how well the amplitude is
        known. The creep input then carries the covariance ``amplitude_std² g gᵀ``, ``g``
        the creep per unit ``c`` of the kept moves, which widens the predicted offset
        and the measurement noise after a large move instead of gating every
        measurement out when ``c`` is off. 0 treats the input as exact.
    tau_std : float
        Standard deviation of ``ln τ`` (``>= 0``): how well the time constant is known.
        Seconds after a move ``s`` its creep is ``c s (log10 t - log10 τ)``: an error of
        ``τ`` is an offset ``c s δ(ln τ) / ln 10`` along the step that stays, so each
        move widens the estimate by that much (see ``DriftFilter.record_move``).
    """

    amplitude: float = param(0.01, "1/decade", "creep per decade of time, fraction of the step",
                             nonnegative=True)
    tau: float = param(0.1, "s", "creep time constant", positive=True)
    min_step: float = param(500.0, "nm", "shorter moves add no creep term", nonnegative=True)
    rate_tol: float = param(1e-3, "nm/s", "a move creeping slower than this is frozen", positive=True)
    max_moves: int = param(256, "-", "most moves kept", lo=1)
    amplitude_std: float = param(0.0, "1/decade", "standard deviation of the amplitude",
                                 nonnegative=True)
    tau_std: float = param(0.0, "-", "standard deviation of ln tau", nonnegative=True, hi=2.0)

    def __post_init__(self) -> None:
        validate(self)


def creep_offset(t: float, move_times: np.ndarray, move_steps: np.ndarray,
                 amplitude: float, tau: float) -> np.ndarray:
    """Offset added by creep at time ``t``: ``-c Σ s_i log10(1 + max(t - t_i, 0) / τ)``.

    Parameters
    ----------
    t : float
        Time (s), on the same clock as ``move_times``.
    move_times : (n,) array
        Completion times of the moves (s).
    move_steps : (n, 2) array
        Their steps (nm).
    amplitude, tau : float
        ``c`` (per decade) and ``τ`` (s).

    Returns
    -------
    (2,) array
        In nm.
    """
    times = np.asarray(move_times, float).reshape(-1)
    steps = np.asarray(move_steps, float).reshape(-1, 2)
    if times.size == 0:
        return np.zeros(2)
    weights = np.log10(1.0 + np.maximum(t - times, 0.0) / tau)
    return -amplitude * (weights @ steps)


def creep_tau_sensitivity(t: float, move_times: np.ndarray, move_steps: np.ndarray,
                          amplitude: float, tau: float) -> np.ndarray:
    """``∂ creep_offset / ∂ ln τ`` (nm, (2,)) at ``t`` of the moves: ``c/ln 10 Σ s_i x_i/(1 +
    x_i)``, ``x_i = max(t − t_i, 0) / τ``. An error ``λ`` of ``ln τ`` shifts the offset by
    ``λ`` times this (to first order; exactly once ``x ≫ 1``, when the creep is
    ``c s (log10 t − log10 τ)``)."""
    times = np.asarray(move_times, float).reshape(-1)
    if times.size == 0:
        return np.zeros(2)
    x = np.maximum(t - times, 0.0) / tau
    return amplitude / math.log(10.0) * ((x / (1.0 + x)) @ np.asarray(move_steps, float).reshape(-1, 2))


def creep_rate(t: float, move_times: np.ndarray, move_steps: np.ndarray,
               amplitude: float, tau: float) -> np.ndarray:
    """Remaining creep speed of each move at ``t``: ``c |s_i| / (ln 10 (τ + t - t_i))``.

    Returns
    -------
    (n,) array
        In nm/s (the full rate at ``t = t_i`` for moves not yet begun).
    """
    times = np.asarray(move_times, float).reshape(-1)
    lengths = np.hypot(*np.asarray(move_steps, float).reshape(-1, 2).T)
    return amplitude * lengths / (math.log(10.0) * (tau + np.maximum(t - times, 0.0)))


#: Shortest piece (nm) a continuous motion is recorded in when ``min_step`` is shorter.
MIN_PIECE = 100.0
#: Least time (s) between the pieces of a motion: a fast travel (50 µm/s) is recorded in
#: pieces of 2.5 µm, not 500 nm, and its creep is summed over a few moves, not dozens.
MIN_PIECE_TIME = 0.05


def creep_moves(start, xy, t, min_step: float, last: float = -math.inf, rests=()) -> np.ndarray:
    """Where a motion through the points ``xy`` ((n, 2) nm) at times ``t`` ((n,) s, in
    order) is recorded as moves, from ``start``, the end of the last recorded move, made
    at ``last``: the indices, in order, at which

    - the displacement from the last recorded point first reaches ``max(min_step,
      MIN_PIECE)``, at least :data:`MIN_PIECE_TIME` after the last recorded move (a
      piece of the motion), or
    - XY comes to rest (``rests``: indices) at least ``min_step`` from the last recorded
      point (the end of a move).

    Creep is linear in the step, so a motion creeps as the superposition of its pieces,
    each from its own time: a push of several seconds (or legs one after another) has
    crept during itself, and is not one step made at its end. The simulated instrument and
    the drift estimate cut the same commanded path the same way."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    t = np.asarray(t, float).reshape(-1)
    rests = np.sort(np.asarray(rests, np.int64).reshape(-1))
    piece = max(float(min_step), MIN_PIECE)
    here = np.asarray(start, float).reshape(2)
    out, k0, n = [], 0, len(xy)
    while k0 < n:
        k1 = max(k0, int(np.searchsorted(t, last + MIN_PIECE_TIME - TIME_TOLERANCE, side="left")))
        hit = np.flatnonzero(np.hypot(*(xy[k1:] - here).T) >= piece)
        k = k1 + int(hit[0]) if hit.size else n
        r = rests[(rests >= k0) & (rests < k)]
        ended = np.flatnonzero(np.hypot(*(xy[r] - here).T) >= max(float(min_step), 1e-9)) if r.size else ()
        if len(ended):
            k = int(r[ended[0]])
        elif k == n:
            break
        out.append(k)
        here, last, k0 = xy[k], t[k], k + 1
    return np.asarray(out, np.int64)


#: A move this much (s) before the last recorded one is taken as made at the same time:
#: instrument times summed in another order differ in the last bits (1e-12 s at 5000 s).
TIME_TOLERANCE = 1e-6


class CreepHistory:
    """The recent large moves and the frozen creep of the older ones.

    Times are in s on the caller's clock (the drift filter passes times relative to its
    epoch). Moves must be recorded in time order (to :data:`TIME_TOLERANCE`).
    """

    def __init__(self, params: CreepModelParams):
        self.params = params
        self.old = FrozenMoves(params.tau)  # the moves no longer kept, still creeping
        # a constant creep and its steps from a checkpoint of before FrozenMoves (moves
        # frozen then stopped creeping); zero otherwise
        self.frozen = np.zeros(2)
        self.frozen_steps = np.zeros(2)
        # the kept moves, the first _n rows of buffers that grow by doubling: a move is
        # written after the rows handed out (read-only views of them never change), and
        # freezing makes new buffers
        self._t = np.empty(16)
        self._s = np.empty((16, 2))
        self._n = 0
        self.version = 0                    # one more at every change of the moves, kept or frozen
        self._cache: tuple | None = None    # (version, times, steps): the kept moves as views
        self._memos: tuple | None = None    # (version, {(what, t): value})

    def _kept(self) -> tuple[np.ndarray, np.ndarray]:
        """The kept moves as read-only arrays (views of the buffers' first rows)."""
        if self._cache is None or self._cache[0] != self.version:
            times, steps = self._t[:self._n], self._s[:self._n]
            times.flags.writeable = steps.flags.writeable = False
            self._cache = (self.version, times, steps)
        return self._cache[1], self._cache[2]

    @property
    def times(self) -> np.ndarray:
        """(n,) array: completion times of the kept moves (read-only)."""
        return self._kept()[0]

    @property
    def steps(self) -> np.ndarray:
        """(n, 2) array: their steps (nm; read-only)."""
        return self._kept()[1]

    def __len__(self) -> int:
        return self._n

    def record(self, t: float, step) -> bool:
        """Keep the move ``step`` (nm) completed at ``t`` if it is long enough.

        Returns
        -------
        bool
            Whether the move was kept (long enough and creep switched on).
        """
        sx, sy = (float(v) for v in np.asarray(step, float).reshape(2))
        if not all(math.isfinite(v) for v in (t, sx, sy)):
            raise ValueError("move time and step must be finite")
        last = float(self._t[self._n - 1]) if self._n else None
        if last is not None and t < last:
            if t < last - TIME_TOLERANCE:
                raise ValueError(f"moves must be recorded in time order: t={t} precedes "
                                 f"the last move at {last}")
            t = last                     # the same instant, summed another way round
        p = self.params
        if p.amplitude == 0.0 or math.hypot(sx, sy) < p.min_step:
            return False
        self.prune(t)
        n = self._n
        if n == self._t.size:
            self._t = np.concatenate([self._t, np.empty(n)])
            self._s = np.concatenate([self._s, np.empty((n, 2))])
        self._t[n] = float(t)
        self._s[n] = (sx, sy)
        self._n = n + 1
        self.version += 1
        if self._n > p.max_moves:     # the oldest, once old enough to bin (FROZEN_AGE)
            self._freeze((np.arange(self._n) < self._n - p.max_moves)
                         & (self.times <= t - FROZEN_AGE), t)
        return True

    def restore(self, old: dict, frozen=(0.0, 0.0), frozen_steps=(0.0, 0.0)) -> None:
        """Take the frozen moves of a checkpoint: ``old``, :meth:`FrozenMoves.state`'s;
        ``frozen``, ``frozen_steps``, the constant creep of one from before
        :class:`FrozenMoves`."""
        self.old = FrozenMoves.from_state(self.params.tau, old)
        self.frozen = np.asarray(frozen, float).reshape(2)
        self.frozen_steps = np.asarray(frozen_steps, float).reshape(2)
        self.version += 1

    def frozen_offset(self, t: float) -> np.ndarray:
        """(2,) array: the creep input (nm) at ``t`` of the moves no longer kept."""
        return self.frozen - self.params.amplitude * self.old(t)

    def frozen_rate(self, t: float) -> np.ndarray:
        """(2,) array: the time derivative (nm/s) of :meth:`frozen_offset` at ``t``."""
        return -self.params.amplitude * self.old.rate(t)

    def _memo(self, what: str, t: float, make) -> np.ndarray:
        """``make()`` for ``what`` at ``t``, kept while the moves stand: a prediction asks
        for the same time's creep several times over (a choice of reference, for each
        candidate)."""
        if self._memos is None or self._memos[0] != self.version:
            self._memos = (self.version, {})
        known = self._memos[1]
        if (what, t) not in known:
            if len(known) >= 32:
                known.clear()
            known[(what, t)] = make()
        return known[(what, t)].copy()

    def offset(self, t: float) -> np.ndarray:
        """(2,) array: the creep input (nm) at ``t``, frozen part included."""
        p = self.params
        return self._memo("offset", float(t), lambda: self.frozen_offset(t) + creep_offset(
            t, self.times, self.steps, p.amplitude, p.tau))

    def tau_sensitivity(self, t: float) -> np.ndarray:
        """(2,) array: ``∂ offset / ∂ ln τ`` (nm) at ``t`` (:func:`creep_tau_sensitivity`),
        frozen part included."""
        p = self.params
        return self._memo("tau", float(t), lambda: (
            p.amplitude / math.log(10.0) * (self.frozen_steps + self.old.tau_weights(t))
            + creep_tau_sensitivity(t, self.times, self.steps, p.amplitude, p.tau)))

    def cov_sqrt(self, t: float) -> np.ndarray:
        """(2, 1) array: factor of the creep input's covariance at ``t``,
        ``amplitude_std g`` with ``g`` the creep per unit amplitude of the kept moves."""
        p = self.params
        return self._memo("cov", float(t), lambda: p.amplitude_std * creep_offset(
            t, self.times, self.steps, 1.0, p.tau)[:, None])

    def cov(self, t: float) -> np.ndarray:
        """(2, 2) array: covariance (nm²) of the creep input at ``t`` from the uncertain
        amplitude of the kept moves, ``amplitude_std² g gᵀ``."""
        c = self.cov_sqrt(t)
        return c @ c.T

    def prune(self, t: float) -> int:
        """Freeze, at ``t``, the moves whose creep rate is below ``rate_tol``.

        Moves completed after ``t`` are kept. Returns the number of moves frozen.
        """
        if not self._n:
            return 0
        p = self.params
        times = self.times
        slow = (times <= t) & (creep_rate(t, times, self.steps, p.amplitude, p.tau) < p.rate_tol)
        return self._freeze(slow, t)

    def _freeze(self, mask: np.ndarray, t: float) -> int:
        if not mask.any():
            return 0
        times, steps = self.times, self.steps
        self.old.add(t, times[mask], steps[mask])
        keep = ~mask
        self._n = int(keep.sum())
        self._t = np.concatenate([times[keep], np.empty(max(16, self._n) - self._n + 16)])
        self._s = np.concatenate([steps[keep], np.empty((max(16, self._n) - self._n + 16, 2))])
        self.version += 1
        return int(mask.sum())


class CreepingOffset:
    """A predicted drift offset with creep, as a vectorised function of time.

    ``offset(t) = thermal + velocity (t - t_ref) + creep(t)`` where ``creep`` is the
    creep input of the recorded moves *and* of moves still to come at known times (the
    travel a streamed path is about to make), so a push follows the sample while the
    piezo creeps after the travel that brought the tip there. Times are on one clock
    (instrument seconds); the moves are copied, so later records do not change it.

    Moves that ended ``linear_after`` s or more before ``t_ref`` creep slowly and
    smoothly there: they enter as their value and rate at ``t_ref`` (the error of that
    line over a push of ``T`` s is at most ``c |s| T² / (2 ln 10 linear_after²)`` a
    move, 0.1 nm for a 2 µm move, ``T`` = 5 s). The recent ones are exact. ``scale``
    multiplies the history's amplitude (a filter that learnt it: ``(c + δc) / c``).
    """

    def __init__(self, thermal, velocity, t_ref: float, history: CreepHistory, epoch: float = 0.0,
                 pending=(), linear_after: float = 30.0, scale: float = 1.0):
        p = history.params
        self.t_ref = float(t_ref)
        self.amplitude, self.tau = p.amplitude * float(scale), p.tau
        times = np.concatenate([history.times + epoch,
                                np.array([t for t, _ in pending], float).reshape(-1)])
        steps = np.vstack([history.steps, np.array([s for _, s in pending], float).reshape(-1, 2)])
        old = times <= self.t_ref - linear_after
        at_ref = history.frozen_offset(self.t_ref) * float(scale) + creep_offset(
            self.t_ref, times[old], steps[old], self.amplitude, self.tau)
        rate = history.frozen_rate(self.t_ref) * float(scale) - (
            creep_rate(self.t_ref, times[old], steps[old], self.amplitude, self.tau)[:, None]
            * _unit_rows(steps[old])).sum(axis=0)
        self.constant = np.asarray(thermal, float).reshape(2) + at_ref
        self.velocity = np.asarray(velocity, float).reshape(2) + rate
        self.times, self.steps = times[~old], steps[~old]

    def __call__(self, t) -> np.ndarray:
        """Offsets ``(n, 2)`` nm at times ``t`` ``(n,)`` s."""
        t = np.asarray(t, float).reshape(-1)
        out = self.constant + (t - self.t_ref)[:, None] * self.velocity
        if self.times.size:
            w = np.log10(1.0 + np.maximum(t[:, None] - self.times[None, :], 0.0) / self.tau)
            # each time's sum alone: a matrix product's rows depend on how many rows it is
            # given, and the DAC renders a path in blocks that must give each sample as alone
            out = out - self.amplitude * np.column_stack([(w * self.steps[:, 0]).sum(axis=1),
                                                          (w * self.steps[:, 1]).sum(axis=1)])
        return out


def _unit_rows(steps: np.ndarray) -> np.ndarray:
    n = np.hypot(steps[:, 0], steps[:, 1])[:, None]
    return np.divide(steps, n, out=np.zeros_like(steps), where=n > 0)
