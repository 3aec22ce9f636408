"""Rauch–Tung–Striebel smoothing of a drift filter's history, for offline review.

Each history step ``k`` holds the filtered ``(x_k, P_k)``, the prediction
``(x⁻_k, P⁻_k)`` made from step ``k - 1`` over ``dt_k`` and the factor of its process
noise ``Q_k``. The smoother runs backwards with the gain ``C_k = P_k Fᵀ (P⁻_{k+1})⁻¹``
(triangular solves with the factor of ``P⁻``; least squares when it is singular) and
carries the smoothed covariance as a factor of the sum of squares
``(I - C F) P_k (I - C F)ᵀ + C Q C ᵀ + C P^s_{k+1} Cᵀ``, which equals the textbook
``P_k + C (P^s_{k+1} - P⁻_{k+1}) Cᵀ`` but cannot lose positive semidefiniteness.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.linalg import solve_triangular

from .kalman import STATE_DIM, symmetrize, transition
from .square_root import tria


def _gain(L: np.ndarray, F: np.ndarray, L_pred: np.ndarray) -> np.ndarray:
    """``C = P Fᵀ P_pred⁻¹`` with ``P = L Lᵀ`` and ``P_pred = L_pred L_predᵀ``."""
    B = F @ (L @ L.T)  # P_pred Cᵀ = F P
    d = np.abs(np.diag(L_pred))
    if d.min() > 1e-12 * d.max() and d.min() > 0.0:
        Y = solve_triangular(L_pred, B, lower=True)
        return solve_triangular(L_pred.T, Y, lower=False).T
    return np.linalg.lstsq(L_pred @ L_pred.T, B, rcond=None)[0].T


def rts(xs: np.ndarray, Ls: np.ndarray, xs_prior: np.ndarray, Ls_prior: np.ndarray,
        Qs_sqrt: Sequence[np.ndarray], dts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Square-root Rauch–Tung–Striebel smoother over ``K`` filter steps.

    Parameters
    ----------
    xs : (K, 4) array
        Filtered states.
    Ls : (K, 4, 4) array
        Factors of the filtered covariances, ``P_k = L_k L_kᵀ``.
    xs_prior : (K, 4) array
        Predicted states of each step (entry 0 is not used).
    Ls_prior : (K, 4, 4) array
        Lower-triangular factors of the predicted covariances (entry 0 is not used).
    Qs_sqrt : sequence of K (4, j) arrays
        Factors of the noise added over each step (entry 0 is not used).
    dts : (K,) array
        Step lengths (s); entry 0 is not used.

    Returns
    -------
    xs_s : (K, 4) array
    Ls_s : (K, 4, 4) array
        Smoothed states and lower-triangular covariance factors; the last step is the
        filtered one.
    """
    xs = np.asarray(xs, float)
    Ls = np.asarray(Ls, float)
    K = xs.shape[0]
    if xs.shape != (K, STATE_DIM) or Ls.shape != (K, STATE_DIM, STATE_DIM):
        raise ValueError(f"xs and Ls must have shapes (K, 4) and (K, 4, 4), got {xs.shape}, {Ls.shape}")
    xs_s, Ls_s = xs.copy(), Ls.copy()
    eye = np.eye(STATE_DIM)
    for k in range(K - 2, -1, -1):
        F = transition(dts[k + 1])
        C = _gain(Ls[k], F, Ls_prior[k + 1])
        xs_s[k] = xs[k] + C @ (xs_s[k + 1] - xs_prior[k + 1])
        Ls_s[k] = tria(np.hstack([(eye - C @ F) @ Ls[k], C @ Qs_sqrt[k + 1], C @ Ls_s[k + 1]]))
    return xs_s, Ls_s


@dataclass(frozen=True)
class SmoothedTrack:
    """Smoothed drift over a run.

    Attributes
    ----------
    t : (K,) array
        Times (s).
    x : (K, 4) array
        Smoothed thermal state ``[dx, dy, vx, vy]`` (nm, nm/s).
    P : (K, 4, 4) array
        Its covariance.
    offset : (K, 2) array
        Smoothed offset, creep input included (nm).
    offset_cov : (K, 2, 2) array
        Its covariance (nm²), the creep input's included.
    """

    t: np.ndarray
    x: np.ndarray
    P: np.ndarray
    offset: np.ndarray
    offset_cov: np.ndarray


def smooth(history: Sequence) -> SmoothedTrack:
    """Smooth a :class:`~nanoasm.drift.DriftFilter` history (its ``history`` list).

    Parameters
    ----------
    history : sequence of HistoryEntry
        At least one entry, in time order.
    """
    if len(history) == 0:
        raise ValueError("history must hold at least one entry")
    xs_s, Ls_s = rts(np.array([h.x for h in history]), np.array([h.P_sqrt for h in history]),
                     np.array([h.x_prior for h in history]),
                     np.array([h.P_prior_sqrt for h in history]), [h.Q_sqrt for h in history],
                     np.array([h.dt for h in history]))
    P = symmetrize(Ls_s @ np.swapaxes(Ls_s, 1, 2))
    creep = np.array([h.creep for h in history])
    return SmoothedTrack(np.array([h.t for h in history]), xs_s, P, xs_s[:, :2] + creep,
                         P[:, :2, :2] + np.array([h.creep_cov for h in history]))
