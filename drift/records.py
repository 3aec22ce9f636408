"""Value types the drift filter returns and keeps: estimates, history, measurement log."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np


class OffsetEstimate(NamedTuple):
    """Offset (nm, creep included) and its 2×2 covariance (nm²) at one time."""

    offset: np.ndarray
    cov: np.ndarray


class HistoryEntry(NamedTuple):
    """One step of the filter, for review and smoothing.

    Attributes
    ----------
    t : float
        Absolute time (s).
    x : (4,) array
        Filtered thermal state.
    P : (4, 4) array
        Its covariance (``P_sqrt P_sqrtᵀ``).
    x_prior, P_prior : (4,), (4, 4) arrays
        The state predicted from the previous entry over ``dt``.
    dt : float
        Step from the previous entry (s).
    creep : (2,) array
        Creep input at ``t`` (nm).
    creep_cov : (2, 2) array
        Its covariance (nm²).
    kind : str
        ``"start"``, ``"predict"``, ``"measure"``, ``"inflate"``, ``"reset"`` (re-initialised) or ``"resume"``.
    P_sqrt, P_prior_sqrt : (4, 4) arrays
        Lower-triangular factors of ``P`` and ``P_prior``.
    Q_sqrt : (4, k) array
        Factor of the noise added over the step (drift-jump widening included).
    """

    t: float
    x: np.ndarray
    P: np.ndarray
    x_prior: np.ndarray
    P_prior: np.ndarray
    dt: float
    creep: np.ndarray
    creep_cov: np.ndarray
    kind: str
    P_sqrt: np.ndarray
    P_prior_sqrt: np.ndarray
    Q_sqrt: np.ndarray


@dataclass(frozen=True)
class Measurement:
    """Outcome of one measured offset.

    Attributes
    ----------
    t : float
        Time (s).
    z : (2,) array, or (m,) for a projected measurement
        The measured offset (nm), creep included, or its components along ``directions``.
    R : (2, 2) array, or (m, m)
        Its covariance (nm²).
    accepted : bool
        Folded into the drift estimate.
    reason : str
        ``"accepted"``; ``"gated"`` (a lone measurement failed the χ² gate: the object
        moved on its own, or the drift jumped); ``"outlier"`` (measured with others, it
        disagreed with them and the prior: the object moved on its own).
    nis : float
        Its own NIS against the prior used (χ², 2 dof; ``m`` for a projected one).
    threshold : float
        The gate on ``nis``.
    innovation : (2,) array, or (m,)
        Measured minus predicted offset (nm), creep taken out.
    S : (2, 2) array, or (m, m)
        Innovation covariance (nm²).
    label : str or None
        The caller's name for the object or landmark.
    drift_jump : bool
        Accepted only after the filter concluded that the drift had jumped (objects
        agreeing with one another against the prior) and widened its prior.
    """

    t: float
    z: np.ndarray
    R: np.ndarray
    accepted: bool
    reason: str
    nis: float
    threshold: float
    innovation: np.ndarray
    S: np.ndarray
    label: str | None = None
    drift_jump: bool = False
    directions: np.ndarray | None = None


@dataclass(frozen=True)
class JointMeasurement:
    """Outcome of the offsets measured at one time.

    Attributes
    ----------
    t : float
        Time (s).
    results : tuple of Measurement
        In input order.
    joint_nis : float
        NIS of the accepted ones together, χ² with ``dof`` degrees of freedom.
    dof : int
    drift_jump : bool
        The filter concluded that the drift jumped and widened its prior: a consistent
        majority overruled it, or consecutive rejected measurements of different objects
        agreed with one another (then see ``readmitted``).
    readmitted : tuple of Measurement
        Earlier measurements, first gated out, now folded in after all: their objects
        did not move after all. Their records here carry the re-evaluated NIS.
    """

    t: float
    results: tuple[Measurement, ...]
    joint_nis: float
    dof: int
    drift_jump: bool
    readmitted: tuple[Measurement, ...] = ()

    @property
    def accepted(self) -> np.ndarray:
        """(n,) bool array."""
        return np.array([r.accepted for r in self.results], bool)
