"""Drift and creep models and the Kalman filter that tracks them.

Start with :class:`DriftFilter` (configured by :class:`DriftFilterParams`); the pure
functions underneath are the covariance forms in :mod:`.kalman`, the square-root forms
in :mod:`.square_root`, the χ² gates in :mod:`.gating`, the creep input in
:mod:`.creep` and the Rauch–Tung–Striebel smoother in :mod:`.smoother`.
"""

from .creep import CreepHistory, CreepModelParams, creep_offset, creep_rate
from .drift_filter import DriftFilter, DriftFilterParams
from .gating import (
    Selection,
    fuse,
    gate,
    gate_threshold,
    joint_nis,
    leave_one_out_nis,
    nis,
    nis_sqrt,
    select_consistent,
    weighted_mean,
)
from .kalman import (
    H_OFFSET,
    STATE_DIM,
    UpdateResult,
    predict,
    process_noise,
    process_noise_sqrt,
    symmetrize,
    transition,
    update,
)
from .records import HistoryEntry, JointMeasurement, Measurement, OffsetEstimate
from .smoother import SmoothedTrack, rts, smooth
from .square_root import SqrtUpdateResult, predict_sqrt, psd_sqrt, tria, update_sqrt

__all__ = [
    "H_OFFSET", "STATE_DIM", "CreepHistory", "CreepModelParams", "DriftFilter",
    "DriftFilterParams", "HistoryEntry", "JointMeasurement", "Measurement", "OffsetEstimate",
    "Selection", "SmoothedTrack", "SqrtUpdateResult", "UpdateResult", "creep_offset",
    "creep_rate", "fuse", "gate", "gate_threshold", "joint_nis", "leave_one_out_nis", "nis",
    "nis_sqrt", "predict", "predict_sqrt", "process_noise", "process_noise_sqrt", "psd_sqrt",
    "rts", "select_consistent", "smooth", "symmetrize", "transition", "tria", "update",
    "update_sqrt", "weighted_mean",
]
