"""Innovation gating: telling drift from an object that moved on its own.

A measured offset that drift explains has a normalised innovation squared (NIS) that is
χ²-distributed with 2 degrees of freedom; an object pushed or kicked away gives a far
larger one. :func:`gate` is the single test. :func:`select_consistent` handles several
objects measured at once: all offsets share one drift, so they are tested jointly
against the prior, the worst leave-one-out outlier is dropped until the rest agree,
and a majority of objects that agree among themselves but not with the prior is read
as a drift jump (the prior was wrong), not as all those objects having moved.
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import NamedTuple

import numpy as np
from scipy.linalg import LinAlgError, cho_factor, cho_solve, solve_triangular
from scipy.stats import chi2

from .kalman import symmetrize
from .square_root import sqrt_update_core, tria


@lru_cache(maxsize=256)
def gate_threshold(dof: int, p: float) -> float:
    """The ``p`` quantile of χ² with ``dof`` degrees of freedom.

    Parameters
    ----------
    dof : int
        Degrees of freedom, ``>= 1``.
    p : float
        Gate probability in (0, 1), e.g. 0.997.
    """
    if int(dof) != dof or dof < 1:
        raise ValueError(f"dof must be a positive integer, got {dof}")
    if not (0.0 < p < 1.0):
        raise ValueError(f"p must lie in (0, 1), got {p}")
    return float(chi2.ppf(p, int(dof)))


def gate(nis: float, dof: int = 2, p: float = 0.997) -> bool:
    """True when ``nis`` passes the χ² gate (the measurement is consistent).

    Parameters
    ----------
    nis : float
        Normalised innovation squared.
    dof : int
        Its degrees of freedom (2 for one 2-D offset).
    p : float
        Gate probability: a consistent measurement passes with probability ``p``.
    """
    if math.isnan(nis):
        raise ValueError("nis must be a number, got nan")
    return nis <= gate_threshold(dof, p)


def nis(innovation: np.ndarray, S: np.ndarray) -> float:
    """``innovationᵀ S⁻¹ innovation`` through the Cholesky factor of ``S``.

    Parameters
    ----------
    innovation : (m,) array
    S : (m, m) array
        Symmetric positive definite.
    """
    try:
        factor = cho_factor(symmetrize(np.asarray(S, float)), lower=True)
    except LinAlgError:
        raise ValueError("S must be symmetric positive definite") from None
    v = np.asarray(innovation, float)
    return float(v @ cho_solve(factor, v))


def nis_sqrt(innovation: np.ndarray, S_sqrt: np.ndarray) -> float:
    """``‖S_sqrt⁻¹ innovation‖²``, the NIS from a lower-triangular factor of ``S``."""
    w = solve_triangular(np.asarray(S_sqrt, float), np.asarray(innovation, float), lower=True)
    return float(w @ w)


def _block_sqrt(Rs: np.ndarray) -> np.ndarray:
    """Block-diagonal Cholesky factor of independent ``Rs`` (n, 2, 2)."""
    n = Rs.shape[0]
    out = np.zeros((2 * n, 2 * n))
    for i, R in enumerate(Rs):
        try:
            out[2 * i:2 * i + 2, 2 * i:2 * i + 2] = np.linalg.cholesky(symmetrize(R))
        except np.linalg.LinAlgError:
            raise ValueError(f"Rs[{i}] must be symmetric positive definite") from None
    return out


def joint_nis(z_pred: np.ndarray, P_sqrt: np.ndarray, zs: np.ndarray, Rs: np.ndarray) -> float:
    """NIS of ``n`` offsets measured at once (χ² with ``2 n`` dof).

    Each ``zs[i] = d + v_i`` with one shared offset ``d ~ N(z_pred, P)`` and independent
    ``v_i ~ N(0, Rs[i])``: the joint innovation covariance is ``P`` in every 2×2 block
    plus ``Rs[i]`` on the diagonal. It is factored from ``[1 ⊗ P_sqrt, blockdiag(R_i^½)]``
    by one QR, so a singular or huge ``P`` is fine.

    Parameters
    ----------
    z_pred : (2,) array
        Predicted offset (nm).
    P_sqrt : (2, k) array
        Factor of its covariance, ``P = P_sqrt P_sqrtᵀ`` (see :func:`~nanoasm.drift.psd_sqrt`).
    zs : (n, 2) array
        Measured offsets.
    Rs : (n, 2, 2) array
        Their covariances, each positive definite.
    """
    zs = np.asarray(zs, float).reshape(-1, 2)
    Rs = np.asarray(Rs, float).reshape(-1, 2, 2)
    n = zs.shape[0]
    S_sqrt = tria(np.hstack([np.kron(np.ones((n, 1)), np.asarray(P_sqrt, float)), _block_sqrt(Rs)]))
    return nis_sqrt((zs - z_pred).reshape(-1), S_sqrt)


def fuse(z_pred: np.ndarray, P_sqrt: np.ndarray, zs: np.ndarray,
         Rs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Posterior of the shared offset from a prior and ``n`` measurements.

    Parameters
    ----------
    z_pred : (2,) array
    P_sqrt : (2, k) array
        Factor of the prior covariance.
    zs : (n, 2) array
    Rs : (n, 2, 2) array

    Returns
    -------
    mean : (2,) array
    cov_sqrt : (2, 2) array
        Lower-triangular factor of the posterior covariance (the prior's with ``n = 0``).
    """
    zs = np.asarray(zs, float).reshape(-1, 2)
    Rs = np.asarray(Rs, float).reshape(-1, 2, 2)
    L = np.asarray(P_sqrt, float)
    if zs.shape[0] == 0:
        return np.asarray(z_pred, float).copy(), tria(L)
    H = np.kron(np.ones((zs.shape[0], 1)), np.eye(2))
    mean, L_new, *_ = sqrt_update_core(np.asarray(z_pred, float), L, zs.reshape(-1),
                                       _block_sqrt(Rs), H)
    return mean, L_new


def leave_one_out_nis(z_pred: np.ndarray, P_sqrt: np.ndarray, zs: np.ndarray,
                      Rs: np.ndarray) -> np.ndarray:
    """NIS of each measurement against the prior fused with all the others.

    Returns
    -------
    (n,) array
        χ² with 2 dof each when everything is consistent.
    """
    zs = np.asarray(zs, float).reshape(-1, 2)
    Rs = np.asarray(Rs, float).reshape(-1, 2, 2)
    out = np.empty(zs.shape[0])
    for i in range(zs.shape[0]):
        keep = np.arange(zs.shape[0]) != i
        m, L = fuse(z_pred, P_sqrt, zs[keep], Rs[keep])
        out[i] = nis_sqrt(zs[i] - m, tria(np.hstack([L, np.linalg.cholesky(symmetrize(Rs[i]))])))
    return out


def weighted_mean(zs: np.ndarray, Rs: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Information-weighted mean of ``n`` offsets and how far they disagree (no prior).

    Parameters
    ----------
    zs : (n, 2) array
    Rs : (n, 2, 2) array
        Each positive definite.

    Returns
    -------
    mean : (2,) array
        ``z̄ = (Σ R_i⁻¹)⁻¹ Σ R_i⁻¹ z_i``.
    cov : (2, 2) array
        ``(Σ R_i⁻¹)⁻¹``.
    dispersion : float
        ``Σ (z_i - z̄)ᵀ R_i⁻¹ (z_i - z̄)``, χ² with ``2 (n - 1)`` dof.
    """
    zs = np.asarray(zs, float).reshape(-1, 2)
    Rs = np.asarray(Rs, float).reshape(-1, 2, 2)
    factors = [cho_factor(symmetrize(R), lower=True) for R in Rs]
    info = symmetrize(sum(cho_solve(f, np.eye(2)) for f in factors))
    rhs = sum(cho_solve(f, z) for f, z in zip(factors, zs))
    info_factor = cho_factor(info, lower=True)
    mean = cho_solve(info_factor, rhs)
    cov = symmetrize(cho_solve(info_factor, np.eye(2)))
    spread = float(sum((z - mean) @ cho_solve(f, z - mean) for f, z in zip(factors, zs)))
    return mean, cov, spread


class Selection(NamedTuple):
    """Result of :func:`select_consistent`.

    Attributes
    ----------
    accepted : (n,) bool array
        Measurements consistent with the (possibly widened) prior and one another.
    joint_nis : float
        Joint NIS of the accepted ones (0 when none is).
    dof : int
        Its degrees of freedom, ``2 * accepted.sum()``.
    jump : (2,) array
        Zero, or on a drift jump the consensus innovation ``e`` (nm): the prior offset
        covariance was widened by ``e eᵀ`` before the final test.
    drift_jump : bool
        A strict majority of at least ``min_consensus`` objects agreed among themselves
        but not with the prior.
    """

    accepted: np.ndarray
    joint_nis: float
    dof: int
    jump: np.ndarray
    drift_jump: bool


def _anchored(z_pred, P_sqrt, zs, Rs, p) -> tuple[np.ndarray, float]:
    """Drop the worst leave-one-out outlier until the rest pass the joint gate."""
    keep = np.ones(zs.shape[0], bool)
    while keep.any():
        idx = np.flatnonzero(keep)
        value = joint_nis(z_pred, P_sqrt, zs[idx], Rs[idx])
        if gate(value, 2 * idx.size, p):
            return keep, value
        if idx.size == 1:
            keep[idx[0]] = False
            break
        loo = leave_one_out_nis(z_pred, P_sqrt, zs[idx], Rs[idx])
        keep[idx[int(np.argmax(loo))]] = False
    return keep, 0.0


def select_consistent(z_pred: np.ndarray, P_sqrt: np.ndarray, zs: np.ndarray, Rs: np.ndarray,
                      p: float = 0.997, min_consensus: int = 2) -> Selection:
    """Pick the offsets that drift explains; the others belong to objects that moved.

    Parameters
    ----------
    z_pred : (2,) array
        Predicted offset (nm).
    P_sqrt : (2, k) array
        Factor of its covariance (nm), ``P = P_sqrt P_sqrtᵀ``.
    zs : (n, 2) array
        Offsets measured at the same time (objects or landmarks).
    Rs : (n, 2, 2) array
        Their covariances (nm²).
    p : float
        Gate probability.
    min_consensus : int
        Smallest number of mutually consistent rejected objects, also a strict majority,
        that is read as a drift jump rather than as objects moving. ``0`` turns the
        drift-jump rule off.

    Returns
    -------
    Selection
    """
    zs = np.asarray(zs, float).reshape(-1, 2)
    Rs = np.asarray(Rs, float).reshape(-1, 2, 2)
    z_pred = np.asarray(z_pred, float)
    P_sqrt = np.asarray(P_sqrt, float).reshape(2, -1)
    if int(min_consensus) != min_consensus or min_consensus < 0:
        raise ValueError(f"min_consensus must be a non-negative integer, got {min_consensus}")
    keep, value = _anchored(z_pred, P_sqrt, zs, Rs, p)
    jump = np.zeros(2)
    out = ~keep
    k = int(out.sum())
    is_jump = (min_consensus > 0 and k >= max(min_consensus, 2) and k > zs.shape[0] - k
               and gate(weighted_mean(zs[out], Rs[out])[2], 2 * (k - 1), p))
    if is_jump:
        jump = weighted_mean(zs[out], Rs[out])[0] - z_pred
        keep, value = _anchored(z_pred, np.hstack([P_sqrt, jump[:, None]]), zs, Rs, p)
    return Selection(keep, float(value), 2 * int(keep.sum()), jump, bool(is_jump))
