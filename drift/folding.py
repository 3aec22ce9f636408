"""Joint measurements of the whole offset (objects measured at one time), as pure
functions for :class:`~nanoasm.drift.drift_filter.DriftFilter`: a batch of offsets,
the consistent ones selected against the prior (or a drift jump read from their
agreement) and folded in, square-root form throughout."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .gating import Selection, gate_threshold, nis_sqrt, select_consistent
from .kalman import H_OFFSET, STATE_DIM, process_noise_sqrt, symmetrize
from .records import Measurement
from .square_root import predict_sqrt, tria, update_sqrt


class Batch(NamedTuple):
    """Offsets measured at one time, with the creep input at that time."""

    tau: float
    t: float
    zs: np.ndarray
    thermal: np.ndarray
    Rs: np.ndarray
    creep: np.ndarray
    creep_sqrt: np.ndarray
    labels: tuple


class Folded(NamedTuple):
    x: np.ndarray
    L: np.ndarray
    x_prior: np.ndarray
    L_prior: np.ndarray
    Q_sqrt: np.ndarray
    sel: Selection
    results: tuple[Measurement, ...]


def fold(p, x0: np.ndarray, L0: np.ndarray, dt: float, batch: Batch,
          widen: np.ndarray | None) -> Folded:
    """Predict ``(x0, L0)`` over ``dt``, widen the prior by the columns ``widen``, select
    the consistent offsets of ``batch`` and fold them in. Pure."""
    x_prior, L_prior = predict_sqrt(x0, L0, dt, p.q, p.q_offset)
    Q_sqrt = process_noise_sqrt(dt, p.q, p.q_offset)
    if widen is not None:
        L_prior = tria(np.hstack([L_prior, widen]))
        Q_sqrt = np.hstack([Q_sqrt, widen])
    prior_sqrt = np.hstack([L_prior[:2], batch.creep_sqrt])  # creep error: common to all
    sel = select_consistent(x_prior[:2], prior_sqrt, batch.thermal, batch.Rs,
                            p.gate_probability, p.min_consensus)
    if sel.drift_jump:  # widen the prior by the consensus innovation
        column = np.zeros((STATE_DIM, 1))
        column[:2, 0] = sel.jump
        L_prior = tria(np.hstack([L_prior, column]))
        Q_sqrt = np.hstack([Q_sqrt, column])
        prior_sqrt = np.hstack([L_prior[:2], batch.creep_sqrt])
    x, L = x_prior, L_prior
    idx = np.flatnonzero(sel.accepted)
    if idx.size:
        creep_cov = batch.creep_sqrt @ batch.creep_sqrt.T
        R_block = np.kron(np.ones((idx.size, idx.size)), creep_cov)
        for j, i in enumerate(idx):
            R_block[2 * j:2 * j + 2, 2 * j:2 * j + 2] += batch.Rs[i]
        x, L = update_sqrt(x_prior, L_prior, batch.thermal[idx].reshape(-1), R_block,
                           np.vstack([H_OFFSET] * idx.size))[:2]
    threshold = gate_threshold(2, p.gate_probability)
    n = batch.zs.shape[0]
    results = []
    for i in range(n):
        innovation = batch.thermal[i] - x_prior[:2]
        S_sqrt = tria(np.hstack([prior_sqrt, np.linalg.cholesky(batch.Rs[i])]))
        ok = bool(sel.accepted[i])
        reason = "accepted" if ok else ("gated" if n == 1 else "outlier")
        results.append(Measurement(batch.t, batch.zs[i].copy(), batch.Rs[i].copy(), ok, reason,
                                   nis_sqrt(innovation, S_sqrt), threshold, innovation,
                                   gram(S_sqrt), batch.labels[i], ok and sel.drift_jump))
    return Folded(x, L, x_prior, L_prior, Q_sqrt, sel, tuple(results))


def gram(L: np.ndarray) -> np.ndarray:
    """``L Lᵀ``, exactly symmetric."""
    return symmetrize(L @ L.T)
