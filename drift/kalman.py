"""Pure Kalman filter functions for the drift state ``x = [dx, dy, vx, vy]`` (nm, nm/s).

The offset ``(dx, dy)`` of the scanner frame relative to the layout frame moves with a
velocity ``(vx, vy)`` whose random walk has intensity ``q`` (nm²/s³; a drift with a
velocity random walk of ``w`` nm/s per √s has ``q = w²``). Optional white noise of
intensity ``q_offset`` (nm²/s) acts on the offset itself. Both are discretised exactly
for any step ``dt >= 0`` (s), long gaps included.

Measurements are offsets: the position of an object (or a fixed landmark) found by a
local scan in the scanner frame minus its believed position in the layout frame, with
the scan's 2×2 covariance ``R`` (nm²). The covariance update is Joseph's form and every
linear system is solved through a Cholesky factor; no matrix is inverted explicitly.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from scipy.linalg import LinAlgError, cho_factor, cho_solve

#: Number of state components: ``[dx, dy, vx, vy]``.
STATE_DIM = 4
#: Measurement matrix of an offset measurement, ``(2, 4)``.
H_OFFSET = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]])


class UpdateResult(NamedTuple):
    """Result of :func:`update`.

    Attributes
    ----------
    x : (4,) array
        Updated state.
    P : (4, 4) array
        Updated covariance (Joseph form, symmetric).
    innovation : (m,) array
        ``z - H x`` with the prior ``x`` (nm).
    S : (m, m) array
        Innovation covariance ``H P Hᵀ + R`` (nm²).
    nis : float
        Normalised innovation squared ``innovationᵀ S⁻¹ innovation`` (χ² with m dof).
    """

    x: np.ndarray
    P: np.ndarray
    innovation: np.ndarray
    S: np.ndarray
    nis: float


def symmetrize(A: np.ndarray) -> np.ndarray:
    """``(A + Aᵀ) / 2``."""
    return 0.5 * (A + np.swapaxes(A, -1, -2))


def _check_dt(dt: float) -> float:
    dt = float(dt)
    if not (math.isfinite(dt) and dt >= 0.0):
        raise ValueError(f"dt must be finite and not negative, got {dt}")
    return dt


def _check_intensity(name: str, value: float) -> float:
    value = float(value)
    if not (math.isfinite(value) and value >= 0.0):
        raise ValueError(f"{name} must be finite and not negative, got {value}")
    return value


def transition(dt: float) -> np.ndarray:
    """Constant-velocity transition matrix ``F(dt)``.

    Parameters
    ----------
    dt : float
        Step in s, ``>= 0``.

    Returns
    -------
    F : (4, 4) array
        ``[[I, dt I], [0, I]]``.
    """
    dt = _check_dt(dt)
    F = np.eye(STATE_DIM)
    F[0, 2] = F[1, 3] = dt
    return F


def process_noise_sqrt(dt: float, q: float, q_offset: float = 0.0) -> np.ndarray:
    """A square root ``L`` of the exact process noise, ``Q(dt) = L Lᵀ``.

    Per axis, the velocity random walk contributes
    ``√q [[dt^1.5/√3, 0], [√3/2 dt^0.5, dt^0.5/2]]`` (whose product with its transpose
    is ``q [[dt³/3, dt²/2], [dt²/2, dt]]``) and the offset white noise ``√(q_offset dt)``.

    Parameters
    ----------
    dt : float
        Step in s, ``>= 0``.
    q : float
        Velocity random-walk intensity in nm²/s³.
    q_offset : float
        Offset white-noise intensity in nm²/s.

    Returns
    -------
    L : (4, 6) array
        Columns 0-3: the random walk (x then y); columns 4-5: the offset noise.
    """
    dt = _check_dt(dt)
    q = _check_intensity("q", q)
    q_offset = _check_intensity("q_offset", q_offset)
    sq, r = math.sqrt(q), math.sqrt(dt)
    block = sq * np.array([[dt * r / math.sqrt(3.0), 0.0], [math.sqrt(3.0) / 2.0 * r, r / 2.0]])
    L = np.zeros((STATE_DIM, 6))
    for axis in (0, 1):
        rows = [axis, axis + 2]
        L[np.ix_(rows, [2 * axis, 2 * axis + 1])] = block
        L[axis, 4 + axis] = math.sqrt(q_offset * dt)
    return L


def process_noise(dt: float, q: float, q_offset: float = 0.0) -> np.ndarray:
    """Exact process noise ``Q(dt)`` of the constant-velocity model.

    ``Q = ∫₀^dt F(s) G q Gᵀ F(s)ᵀ ds + q_offset dt diag(1, 1, 0, 0)``, that is per axis
    ``q [[dt³/3, dt²/2], [dt²/2, dt]]`` plus ``q_offset dt`` on the offset. Built as
    ``L Lᵀ`` (see :func:`process_noise_sqrt`), so it is symmetric positive semidefinite
    by construction for every ``dt``, 0 and 10⁵ s included.

    Returns
    -------
    Q : (4, 4) array
        In nm², nm²/s and nm²/s².
    """
    L = process_noise_sqrt(dt, q, q_offset)
    return symmetrize(L @ L.T)


def _check_state(x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(x, dtype=float)
    P = np.asarray(P, dtype=float)
    if x.shape != (STATE_DIM,):
        raise ValueError(f"x must have shape (4,), got {x.shape}")
    if P.shape != (STATE_DIM, STATE_DIM):
        raise ValueError(f"P must have shape (4, 4), got {P.shape}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(P))):
        raise ValueError("x and P must be finite")
    return x, P


def predict(x: np.ndarray, P: np.ndarray, dt: float, q: float,
            q_offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Propagate the state over ``dt`` seconds.

    Parameters
    ----------
    x : (4,) array
        State ``[dx, dy, vx, vy]`` (nm, nm/s).
    P : (4, 4) array
        Its covariance.
    dt : float
        Step in s, ``>= 0``.
    q, q_offset : float
        Process-noise intensities (nm²/s³, nm²/s), see :func:`process_noise`.

    Returns
    -------
    x : (4,) array
        ``F x``.
    P : (4, 4) array
        ``F P Fᵀ + Q``, symmetrised.
    """
    x, P = _check_state(x, P)
    F = transition(dt)
    return F @ x, symmetrize(F @ P @ F.T + process_noise(dt, q, q_offset))


def _check_measurement(z, R, H) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    H = np.asarray(H, dtype=float)
    if H.ndim != 2 or H.shape[1] != STATE_DIM:
        raise ValueError(f"H must have shape (m, 4), got {H.shape}")
    m = H.shape[0]
    z = np.asarray(z, dtype=float)
    R = np.asarray(R, dtype=float)
    if z.shape != (m,):
        raise ValueError(f"z must have shape ({m},), got {z.shape}")
    if R.shape != (m, m):
        raise ValueError(f"R must have shape ({m}, {m}), got {R.shape}")
    if not (np.all(np.isfinite(z)) and np.all(np.isfinite(R)) and np.all(np.isfinite(H))):
        raise ValueError("z, R and H must be finite")
    R = symmetrize(R)
    try:
        cho_factor(R, lower=True)
    except LinAlgError:
        raise ValueError("R must be symmetric positive definite") from None
    return z, R, H


def _solver(S: np.ndarray, R: np.ndarray):
    """``B ↦ S⁻¹ B`` through Cholesky; if rounding in a huge ``P`` left ``S`` indefinite,
    through its eigendecomposition with eigenvalues raised to ``λ_min(R)`` (the true
    ``S = H P Hᵀ + R`` has none below it)."""
    try:
        factor = cho_factor(S, lower=True)
        return lambda B: cho_solve(factor, B)
    except LinAlgError:
        w, V = np.linalg.eigh(S)
        w = np.maximum(w, np.linalg.eigvalsh(R)[0])
        return lambda B: V @ ((V.T @ B) / (w if np.ndim(B) == 1 else w[:, None]))


def update(x: np.ndarray, P: np.ndarray, z: np.ndarray, R: np.ndarray,
           H: np.ndarray = H_OFFSET) -> UpdateResult:
    """Fold the measurement ``z = H x + v``, ``v ~ N(0, R)``, into the state.

    The gain solves ``K S = P Hᵀ`` through the Cholesky factor of ``S``; the covariance
    is Joseph's form ``(I - K H) P (I - K H)ᵀ + K R Kᵀ``, symmetrised, which stays
    positive semidefinite (to rounding at the scale of ``P``) for a huge prior
    (``P = 1e12 I``) or a nearly singular one. A covariance whose rounding noise
    exceeds ``R`` (entries ~10²⁰ with ``R ~ 1``) cannot carry the answer to full
    precision; the square-root forms in :mod:`nanoasm.drift.square_root` can.

    Parameters
    ----------
    x : (4,) array
        Prior state.
    P : (4, 4) array
        Prior covariance.
    z : (m,) array
        Measurement (nm), e.g. a measured offset.
    R : (m, m) array
        Its covariance (nm²), symmetric positive definite.
    H : (m, 4) array
        Measurement matrix; :data:`H_OFFSET` by default.

    Returns
    -------
    UpdateResult
        ``(x, P, innovation, S, nis)``.

    Raises
    ------
    ValueError
        On wrong shapes, non-finite values or an ``R`` that is not positive definite.
    """
    x, P = _check_state(x, P)
    z, R, H = _check_measurement(z, R, H)
    PHt = P @ H.T
    S = symmetrize(H @ PHt + R)
    solve = _solver(S, R)
    innovation = z - H @ x
    K = solve(PHt.T).T
    nis = float(innovation @ solve(innovation))
    A = np.eye(STATE_DIM) - K @ H
    P_new = symmetrize(A @ P @ A.T + K @ R @ K.T)
    return UpdateResult(x + K @ innovation, P_new, innovation, S, nis)
