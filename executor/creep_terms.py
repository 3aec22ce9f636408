"""What the creep amplitude's uncertainty does to the measurements of a
:class:`~nanoasm.executor.kalman_drift.Kalman` estimate, as free functions over it.

The creep a move brings is known up to its amplitude (a real scanner's to some ±30 %),
which the estimate learns: the full scan's drift model as ``ε`` (relative) during the
bootstrap, the drift filter as ``δc`` (absolute) after. Right after a long travel the
creep runs at tens of nm/s, so a local scan's later lines, shifted by the creep
predicted since its first, err by the amplitude's error times that creep: the located
position carries it, and a drift reference measured so depends on the amplitude's
error through it. Its time constant's error ``λ = δ ln τ`` is learnt too, by the full
scan's model and the filter (``CreepHistory.tau_sensitivity``), not here.
"""

from __future__ import annotations

import math

import numpy as np

from nanoasm.drift.creep import creep_moves

from .scan_drift import EPS


def amplitude_error(est) -> tuple[float, float]:
    """The creep amplitude's relative error as estimated now (what a scan's line
    compensation used) and its variance: the filter's learnt ``δc / c`` once it runs,
    the full scan's model's ``ε`` before."""
    c = est.params.creep.amplitude
    if est.filter.statics and est.filter.learn_creep and c > 0:
        return float(est.filter.x[-1]) / c, float(est.filter.P[-1, -1]) / (c * c)
    return float(est.scan.theta[EPS]), float(est.scan.cov[EPS, EPS])


def compensation(est, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
    """The creep (nm, nominal amplitude) within ``offset(t1) - offset(t0)``, and the
    covariance (nm²) of that difference's error: the creep at the amplitude's
    uncertainty (:func:`amplitude_error`) and the velocity's over the time between. On
    wide seed 1's first bootstrap reference, 66 nm of nominal creep ran between two lines
    0.66 s apart after a 7.5 µm travel: 13 nm 1σ with the amplitude known to 20 %."""
    ep = est.epoch
    d = est.creep_offset(t1 - ep) - est.creep_offset(t0 - ep)
    dt = t1 - t0
    vel = est.filter.P[2:4, 2:4] if est.filter.statics else est.scan.velocity_at(t1 - ep)[1]
    return d, amplitude_error(est)[1] * np.outer(d, d) + dt * dt * np.asarray(vel, float)


def with_creep(est, z, static, creep_sens):
    """A measurement against the full scan whose scan lines' compensation used the creep
    amplitude estimated now: ``z`` and ``static`` with that dependence on the amplitude's
    error (``creep_sens``: nm per unit relative error, one a row of ``static``)."""
    if creep_sens is None or static is None or not est.filter.learn_creep:
        return z, static
    sens = np.asarray(creep_sens, float) / est.params.creep.amplitude
    static = static.copy()
    static[:, -1] += sens
    return np.asarray(z, float) + float(est.filter.x[-1]) * sens, static


def steps_along(est, anchor, xy, t, rests):
    """The moves ``est``'s creep model records of a motion through ``xy`` ((n, 2) nm) at
    ``t`` from ``anchor`` (:func:`~nanoasm.drift.creep.creep_moves`, at least
    ``MIN_PIECE_TIME`` after its last move): their indices and steps (nm)."""
    creep = est.filter.params.creep
    xy = np.asarray(xy, float).reshape(-1, 2)
    if creep.amplitude == 0.0 or not len(xy):
        return np.zeros(0, np.int64), np.zeros((0, 2))
    last = est.move_log[-1][0] if est.move_log else -math.inf
    ks = creep_moves(anchor, xy, t, creep.min_step, last, rests)
    return ks, np.diff(np.vstack([np.asarray(anchor, float).reshape(1, 2), xy[ks]]), axis=0)


__all__ = ["amplitude_error", "compensation", "steps_along", "with_creep"]
