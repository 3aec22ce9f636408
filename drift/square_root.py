"""Square-root (array) forms of the Kalman predict and update.

The covariance is carried as a factor ``L`` with ``P = L Lᵀ``; every step rebuilds the
lower-triangular factor of a sum of squares by one QR decomposition (:func:`tria`), so
the covariance is positive semidefinite by construction and the arithmetic works on
square roots: with a prior of 10¹² nm² and a measurement of 10⁻³ nm² the factor spans
7.5 decades where the covariance would span 15, the limit of float64. The drift filter
runs on these; :mod:`nanoasm.drift.kalman` holds the covariance (Joseph) forms.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.linalg import solve_triangular

from .kalman import (
    H_OFFSET,
    STATE_DIM,
    _check_measurement,
    process_noise_sqrt,
    symmetrize,
    transition,
)


def tria(M: np.ndarray) -> np.ndarray:
    """Lower-triangular ``L`` with ``L Lᵀ = M Mᵀ`` (non-negative diagonal).

    Parameters
    ----------
    M : (n, k) array
        Any factor; ``k < n`` is padded with zero columns.

    Returns
    -------
    L : (n, n) array
    """
    M = np.asarray(M, float)
    n, k = M.shape
    if k < n:
        M = np.hstack([M, np.zeros((n, n - k))])
    L = np.linalg.qr(M.T, mode="r").T
    signs = np.where(np.diag(L) < 0, -1.0, 1.0)
    return L * signs


def psd_sqrt(P: np.ndarray) -> np.ndarray:
    """Lower-triangular factor of a symmetric positive semidefinite ``P``.

    Cholesky when ``P`` is positive definite; otherwise from its eigendecomposition with
    negative rounding-level eigenvalues clipped to zero.

    Parameters
    ----------
    P : (n, n) array

    Returns
    -------
    L : (n, n) array
        ``L Lᵀ = P`` (to rounding).
    """
    P = np.asarray(P, float)
    if P.ndim != 2 or P.shape[0] != P.shape[1] or not np.all(np.isfinite(P)):
        raise ValueError(f"P must be a finite square matrix, got shape {P.shape}")
    P = symmetrize(P)
    try:
        return np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(P)
        if w[0] < -1e-8 * max(abs(w[-1]), np.finfo(float).tiny):
            raise ValueError(f"P is not positive semidefinite (eigenvalue {w[0]:.3g})") from None
        return tria(V * np.sqrt(np.clip(w, 0.0, None)))


class SqrtUpdateResult(NamedTuple):
    """Result of :func:`update_sqrt`: ``x (4,)``, ``L (4, 4)`` with ``P = L Lᵀ``,
    ``innovation (m,)``, ``S_sqrt (m, m)`` lower-triangular with ``S = S_sqrt S_sqrtᵀ``,
    and ``nis``."""

    x: np.ndarray
    L: np.ndarray
    innovation: np.ndarray
    S_sqrt: np.ndarray
    nis: float


def predict_sqrt(x: np.ndarray, L: np.ndarray, dt: float, q: float,
                 q_offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """:func:`~nanoasm.drift.kalman.predict` on a factor: ``L' = tria([F L, L_Q])``.

    Parameters
    ----------
    x : (4,) array
    L : (4, k) array
        Factor of the covariance, ``P = L Lᵀ``.
    dt, q, q_offset : float
        As in :func:`~nanoasm.drift.kalman.predict`.

    Returns
    -------
    x : (4,) array
    L : (4, 4) array
        Lower-triangular.
    """
    x = np.asarray(x, float)
    L = np.asarray(L, float)
    if x.shape != (STATE_DIM,) or L.ndim != 2 or L.shape[0] != STATE_DIM:
        raise ValueError(f"x and L must have shapes (4,) and (4, k), got {x.shape}, {L.shape}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(L))):
        raise ValueError("x and L must be finite")
    F = transition(dt)
    return F @ x, tria(np.hstack([F @ L, process_noise_sqrt(dt, q, q_offset)]))


def sqrt_update_core(x: np.ndarray, L: np.ndarray, z: np.ndarray, R_sqrt: np.ndarray,
                     H: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """Array-form update in any dimension, without input checks.

    One QR of the pre-array ``[[R_sqrt, H L], [0, L]]`` gives ``[[S_sqrt, 0], [K̄, L⁺]]``
    with ``K = K̄ S_sqrt⁻¹``.

    Parameters
    ----------
    x : (n,) array
    L : (n, k) array
        ``P = L Lᵀ``.
    z : (m,) array
    R_sqrt : (m, m) array
        Nonsingular factor of ``R``.
    H : (m, n) array

    Returns
    -------
    x, L, innovation, S_sqrt, nis
    """
    m, n = H.shape
    k = L.shape[1]
    pre = np.zeros((m + n, m + k))
    pre[:m, :m] = R_sqrt
    pre[:m, m:] = H @ L
    pre[m:, m:] = L
    post = tria(pre)
    S_sqrt, Kbar, L_new = post[:m, :m], post[m:, :m], post[m:, m:]
    innovation = z - H @ x
    w = solve_triangular(S_sqrt, innovation, lower=True)
    return x + Kbar @ w, L_new, innovation, S_sqrt, float(w @ w)


def update_sqrt(x: np.ndarray, L: np.ndarray, z: np.ndarray, R: np.ndarray,
                H: np.ndarray = H_OFFSET) -> SqrtUpdateResult:
    """:func:`~nanoasm.drift.kalman.update` on a factor ``L`` (``P = L Lᵀ``).

    Parameters
    ----------
    x : (4,) array
    L : (4, k) array
    z : (m,) array
        Measurement (nm).
    R : (m, m) array
        Its covariance (nm²), symmetric positive definite.
    H : (m, 4) array

    Returns
    -------
    SqrtUpdateResult
        ``(x, L, innovation, S_sqrt, nis)``; ``L`` lower-triangular (4, 4).
    """
    L = np.asarray(L, float)
    if L.ndim != 2 or L.shape[0] != STATE_DIM or not np.all(np.isfinite(L)):
        raise ValueError(f"L must be a finite (4, k) array, got shape {L.shape}")
    x = np.asarray(x, float)
    if x.shape != (STATE_DIM,) or not np.all(np.isfinite(x)):
        raise ValueError(f"x must be a finite (4,) array, got shape {x.shape}")
    z, R, H = _check_measurement(z, R, H)
    return SqrtUpdateResult(*sqrt_update_core(x, L, z, np.linalg.cholesky(R), H))
