"""The stateful drift filter the executor talks to: a thin layer over the pure functions.

:class:`DriftFilter` keeps the state ``[dx, dy, vx, vy]`` (thermal drift only), the creep
history (a known input), the review history and the measurement log. Times are given
on the instrument clock (s) and stored relative to the filter's ``epoch``, so steps stay
exact for clocks around 10⁷ s. Offsets are in nm, in the sense of
``z = measured position in the scanner frame - believed position in the layout frame``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from nanoasm.param import ParamError, number, param, validate

from .creep import CreepHistory, CreepModelParams
from .folding import Batch, Folded, fold, gram
from .gating import gate_threshold, nis_sqrt, weighted_mean
from .kalman import H_OFFSET, STATE_DIM, _check_state, process_noise_sqrt, symmetrize, transition
from .records import HistoryEntry, JointMeasurement, Measurement, OffsetEstimate
from .square_root import predict_sqrt, psd_sqrt, sqrt_update_core, tria


@dataclass(frozen=True)
class DriftFilterParams:
    """Tuning of :class:`DriftFilter`.

    Attributes
    ----------
    q : float
        Velocity random-walk intensity (nm²/s³); a drift whose velocity wanders by
        ``w`` nm/s per √s has ``q = w²``.
    q_offset : float
        White-noise intensity on the offset (nm²/s).
    offset_std : float
        Prior standard deviation of the offset at the epoch (nm, ``> 0``).
    velocity_std : float
        Prior standard deviation of the drift velocity (nm/s, ``> 0``).
    measurement_std : float
        Default standard deviation of a measured offset per axis (nm, ``> 0``).
    gate_probability : float
        χ² gate probability in (0, 1).
    min_consensus : int
        How many different objects must agree with one another against the prior before
        the filter reads a drift jump rather than objects that moved: in one joint
        measurement (see :func:`nanoasm.drift.gating.select_consistent`), or in
        consecutive measurements with nothing accepted between them (at least 2; 0
        disables drift jumps).
    time_tolerance : float
        A time up to this much (s) before the filter's time counts as the same time.
    creep : CreepModelParams
        The creep input.
    """

    q: float = param(1e-6, "nm²/s³", "velocity random-walk intensity", nonnegative=True)
    q_offset: float = param(0.0, "nm²/s", "white-noise intensity on the offset", nonnegative=True)
    offset_std: float = param(10.0, "nm", "prior standard deviation of the offset", positive=True)
    velocity_std: float = param(0.5, "nm/s", "prior standard deviation of the drift velocity", positive=True)
    measurement_std: float = param(2.0, "nm", "default standard deviation of a measured offset per axis",
                                   positive=True)
    gate_probability: float = param(0.997, "-", "χ² gate probability, in (0, 1)", positive=True)
    min_consensus: int = param(2, "-", "objects that must agree to read a drift jump (0: never)",
                               nonnegative=True)
    time_tolerance: float = param(1e-6, "s", "a time this much before the filter's counts as the same",
                                  nonnegative=True)
    creep: CreepModelParams = field(default_factory=CreepModelParams)

    def __post_init__(self) -> None:
        validate(self)
        if not self.gate_probability < 1.0:
            raise ParamError("gate_probability", f"must be below 1, got {self.gate_probability!r}")
        if not isinstance(self.creep, CreepModelParams):
            raise TypeError(f"creep must be a CreepModelParams, got {type(self.creep).__name__}")


class DriftFilter:
    """Kalman filter of the scanner-versus-layout offset, with creep and gating.

    The covariance is carried as a square-root factor (:mod:`nanoasm.drift.square_root`),
    so huge priors, long gaps and precise measurements never make it indefinite.

    Parameters
    ----------
    params : DriftFilterParams
    epoch : float
        Instrument time (s) of the prior; all times are stored relative to it.
    x0 : (4,) array, optional
        Prior state; zero offset and velocity by default.
    P0 : (4, 4) array, optional
        Prior covariance; ``diag(offset_std², offset_std², velocity_std², velocity_std²)``
        by default.
    statics : int
        Static parameters after the drift state (``x0`` and ``P0`` then have ``4 +
        statics`` components): constants that measurements may depend on (e.g. the
        drift a reference image carried), estimated with the drift. Such a filter
        measures through :meth:`measure_projected`.
    start : float
        Time of the prior, s after the epoch.
    learn_creep : bool
        Estimate the creep amplitude's error too, as a last static parameter of prior
        ``creep.amplitude_std`` (appended to ``x0`` and ``P0``; or given with them, when
        ``x0`` has one component more than ``4 + statics``, so that its prior may be
        correlated with the rest): the creep input is then nominal and the offset is
        ``thermal + creep + δc g``, ``g`` the creep per unit amplitude. A measurement
        may depend on ``δc`` beyond the creep now: :meth:`measure_projected`'s
        ``static`` then has one column more, added to ``δc``'s.
    tau_static : int, optional
        Index, among the ``statics``, of ``λ``, the error of the creep time constant's
        logarithm: the offset is then ``thermal + creep + λ h + …``, ``h`` the creep per
        unit ``ln τ`` (:meth:`~nanoasm.drift.creep.CreepHistory.tau_sensitivity`), added
        to that static's row in every measurement and prediction; and a move no longer
        widens the estimate by ``creep.tau_std`` (the state holds that uncertainty).
    """

    def __init__(self, params: DriftFilterParams | None = None, *, epoch: float = 0.0,
                 x0: np.ndarray | None = None, P0: np.ndarray | None = None, statics: int = 0,
                 start: float = 0.0, learn_creep: bool = False, tau_static: int | None = None):
        self.params = params if params is not None else DriftFilterParams()
        number("epoch", epoch)
        number("start", start, nonnegative=True)
        self.statics = int(number("statics", statics, integer=True, lo=0))
        p = self.params
        n = STATE_DIM + self.statics
        self.learn_creep = bool(learn_creep)
        if tau_static is not None and not 0 <= int(tau_static) < self.statics:
            raise ValueError(f"tau_static must index one of the {self.statics} statics, got {tau_static!r}")
        self.tau_static = None if tau_static is None else int(tau_static)
        self.epoch = float(epoch)
        self._tau = float(start)
        self._x = np.zeros(n) if x0 is None else np.asarray(x0, float).copy()
        joint = self.learn_creep and self._x.shape == (n + 1,)    # δc's prior given with the rest
        if joint:
            n += 1
            self.statics += 1
        if self._x.shape != (n,) or not np.all(np.isfinite(self._x)):
            raise ValueError(f"x0 must be a finite ({n},) array, got shape {self._x.shape}")
        if P0 is None:
            if self.statics:
                raise ValueError("P0 must be given with statics")
            P0 = np.diag([p.offset_std**2] * 2 + [p.velocity_std**2] * 2)
        P0 = np.asarray(P0, float)
        if P0.shape != (n, n):
            raise ValueError(f"P0 must be a ({n}, {n}) array, got shape {P0.shape}")
        if self.learn_creep and not joint:  # the creep amplitude's error, last: its prior
            self._x = np.append(self._x, 0.0)
            P0 = np.block([[P0, np.zeros((n, 1))], [np.zeros((1, n)), np.array([[p.creep.amplitude_std**2]])]])
            n += 1
            self.statics += 1
        self._L = psd_sqrt(P0)
        # learnt, the amplitude's uncertainty is the state's; the input itself is nominal
        self.creep = CreepHistory(replace(p.creep, amplitude_std=0.0) if self.learn_creep else p.creep)
        self.history: list[HistoryEntry] = []
        #: steps that revised the estimate other than by time (measurements, resets): a
        #: position converted with it before and after one differs by the revision
        self.revision = 0
        #: every change of the state (time steps too): a value derived from it stands while this does
        self.commits = 0
        self._commit(self._tau, 0.0, self._x, self._L, self._x, self._L, np.zeros((n, 0)), "start")
        self.measurements: list[Measurement] = []
        self._anchor = (0, self._tau)  # history index and tau of the last accepted state
        self._streak: list[Batch] = []  # batches rejected since then
        self.resumed_measurements = 0    # measurements made before a resume
        self._offset_cache: tuple | None = None
        self._propagated: dict = {}        # (state, t) -> _propagate's answer

    # -- saving and resuming ------------------------------------------------------------
    def state_dict(self) -> dict:
        """The estimate, its covariance factor and the creep input (JSON types): what
        :meth:`from_state` needs to go on from here (the history for smoothing and the
        gating streak are not kept)."""
        c = self.creep
        return {"epoch": self.epoch, "tau": self._tau, "x": self._x.tolist(), "L": self._L.tolist(),
                "measured": len(self.measurements), "revision": self.revision,
                "statics": self.statics - int(self.learn_creep),
                "learn_creep": self.learn_creep, "tau_static": self.tau_static,
                "creep": {"frozen": c.frozen.tolist(), "times": c.times.tolist(), "steps": c.steps.tolist(),
                          "frozen_steps": c.frozen_steps.tolist(), "old": c.old.state()}}

    @classmethod
    def from_state(cls, params: DriftFilterParams, state: dict) -> DriftFilter:
        """A filter that goes on from :meth:`state_dict`'s estimate."""
        k, learn = int(state.get("statics", 0)), bool(state.get("learn_creep", False))
        tau = float(state["tau"])
        number("tau", tau)
        if k or learn:
            x, L = np.asarray(state["x"], float), np.asarray(state["L"], float)
            n = STATE_DIM + k + int(learn)
            if x.shape != (n,) or L.shape != (n, n) or not (np.all(np.isfinite(x)) and np.all(np.isfinite(L))):
                raise ValueError(f"x and L must be finite with shapes ({n},) and ({n}, {n})")
            m = n - int(learn)
            f = cls(params, epoch=float(state["epoch"]), x0=x[:m], P0=np.eye(m), statics=k, learn_creep=learn,
                    tau_static=state.get("tau_static"))
        else:
            x, L = _check_state(state["x"], state["L"])      # the factor L checked as P would be
            f = cls(params, epoch=float(state["epoch"]))
        c = state["creep"]
        f.creep.restore(c.get("old", {}), c["frozen"], c.get("frozen_steps", (0.0, 0.0)))
        for t, step in zip(c["times"], c["steps"]):
            f.creep.record(float(t), step)
        f._commit(tau, 0.0, x, L, x, L, np.zeros((x.shape[0], 0)), "resume")
        f._anchor = (len(f.history) - 1, tau)
        f.resumed_measurements = int(state.get("measured", 0))
        f.revision = int(state.get("revision", 0))      # going on is no revision
        return f

    # -- state ----------------------------------------------------------------------------
    @property
    def time(self) -> float:
        """Instrument time (s) of the current estimate."""
        return self.epoch + self._tau

    @property
    def x(self) -> np.ndarray:
        """(4 + statics,) array: current thermal-drift state ``[dx, dy, vx, vy]`` and the
        static parameters (a copy)."""
        return self._x.copy()

    @property
    def P(self) -> np.ndarray:
        """(n, n) array: its covariance."""
        return gram(self._L)

    @property
    def P_sqrt(self) -> np.ndarray:
        """(n, n) array: lower-triangular factor of :attr:`P` (a copy)."""
        return self._L.copy()

    def _relative(self, t: float) -> tuple[float, float]:
        """``(tau, dt)``: ``t`` relative to the epoch, and the step from the filter time."""
        number("t", t)
        tau = float(t) - self.epoch
        dt = tau - self._tau
        if dt < -self.params.time_tolerance:
            raise ValueError(f"t={t} s precedes the filter time {self.time} s; the filter "
                             "only moves forward (use nanoasm.drift.smooth for the past)")
        return max(tau, self._tau), max(dt, 0.0)

    def _sensitivity(self, tau: float) -> np.ndarray:
        """``g``, (2,): the creep input per unit amplitude at ``tau`` (frozen part too)."""
        a = self.params.creep.amplitude
        return self.creep.offset(tau) / a if a > 0 else np.zeros(2)

    def _rows(self, N: np.ndarray, static, tau: float) -> np.ndarray:
        """The measurement matrix of components ``N offset + static θ`` at ``tau``: the
        offset's rows, the static parameters', and the learnt creep amplitude's."""
        m = N.shape[0]
        user = self.statics - int(self.learn_creep)
        S = np.zeros((m, user)) if static is None else np.asarray(static, float)
        extra = np.zeros(m)
        if self.learn_creep and S.shape == (m, user + 1):   # a dependence on δc beyond the creep now
            S, extra = S[:, :user], S[:, user]
        if S.shape != (m, user) or not np.all(np.isfinite(S)) or not np.all(np.isfinite(extra)):
            raise ValueError(f"static must be a finite ({m}, {user}) array")
        if self.tau_static is not None:              # λ: the time constant's error, now
            S = S.copy()
            S[:, self.tau_static] += N @ self.creep.tau_sensitivity(tau)
        parts = [N @ H_OFFSET, S]
        if self.learn_creep:
            parts.append((N @ self._sensitivity(tau) + extra)[:, None])
        return np.hstack(parts)

    def _predict(self, x: np.ndarray, L: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Predict ``(x, L)`` over ``dt``; the static parameters stay as they are."""
        p = self.params
        if not self.statics:
            return predict_sqrt(x, L, dt, p.q, p.q_offset)
        F = np.eye(STATE_DIM + self.statics)
        F[:STATE_DIM, :STATE_DIM] = transition(dt)
        return F @ x, tria(np.hstack([F @ L, self._noise_sqrt(dt)]))

    def _noise_sqrt(self, dt: float) -> np.ndarray:
        p = self.params
        Q = process_noise_sqrt(dt, p.q, p.q_offset)
        return np.vstack([Q, np.zeros((self.statics, Q.shape[1]))])

    def _propagate(self, t: float):
        """``(tau, dt, x, L, Q_sqrt)``: the state predicted to ``t`` (copies; the last few
        kept while the state stands: choosing a reference predicts to one time for every
        candidate)."""
        key = (self.commits, float(t))
        memo = self._propagated
        if key not in memo:
            if len(memo) >= 8:
                memo.clear()
            tau, dt = self._relative(t)
            x, L = self._predict(self._x, self._L, dt)
            memo[key] = (tau, dt, x, L, self._noise_sqrt(dt))
        tau, dt, x, L, Q = memo[key]
        return tau, dt, x.copy(), L.copy(), Q.copy()

    def _commit(self, tau, dt, x, L, x_prior, L_prior, Q_sqrt, kind, creep=None,
                creep_sqrt=None) -> None:
        """Make ``(x, L)`` at ``tau`` the current estimate and log the step."""
        if creep is None:
            creep, creep_sqrt = self.creep.offset(tau), self.creep.cov_sqrt(tau)
        self._tau, self._x, self._L = tau, x.copy(), L.copy()
        self.commits += 1
        if kind not in ("predict", "move", "inflate"):
            self.revision += 1
        self.history.append(HistoryEntry(
            self.epoch + tau, x.copy(), gram(L), x_prior.copy(), gram(L_prior), dt,
            np.asarray(creep, float).copy(), creep_sqrt @ creep_sqrt.T, kind, L.copy(),
            L_prior.copy(), Q_sqrt))

    def predict_to(self, t: float) -> None:
        """Advance the estimate to time ``t`` (s, not before :attr:`time`)."""
        tau, dt, x, L, Q_sqrt = self._propagate(t)
        if dt > 0.0:
            self._commit(tau, dt, x, L, x, L, Q_sqrt, "predict")

    def state_at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Predicted thermal state ``(x (4,), P (4, 4))`` at ``t``; the filter is unchanged."""
        _, _, x, L, _ = self._propagate(t)
        return x, gram(L)

    def offset(self, t: float) -> OffsetEstimate:
        """Predicted offset at ``t`` (creep included) and its covariance; no mutation.

        Returns
        -------
        OffsetEstimate
            ``(offset (2,) nm, cov (2, 2) nm²)``: the believed layout position ``p``
            lies at ``p + offset`` in the scanner frame. The covariance includes the
            creep amplitude's uncertainty (``creep.amplitude_std``).
        """
        c = self.creep
        # the executor asks for the same few times over and over (a scan pattern's first
        # line and each of its lines): answers are kept per time while the state stands
        state = (self.commits, c.version)
        if self._offset_cache is None or self._offset_cache[0] != state:
            self._offset_cache = (state, {}, {})
        known = self._offset_cache[1]
        t = float(t)
        if t not in known:
            if len(known) >= 16:
                known.clear()
            tau, _, x, L, _ = self._propagate(t)
            O = self._rows(np.eye(2), None, tau)
            known[t] = (O @ x + c.offset(tau), gram(np.hstack([O @ L, c.cov_sqrt(tau)])))
        off, cov = known[t]
        return OffsetEstimate(off.copy(), cov.copy())

    def offset_mean(self, t: float) -> np.ndarray:
        """``offset(t).offset`` to the bit, without its covariance (the state alone is
        predicted: no factor's QR, no Gram matrix); answers kept like :meth:`offset`'s."""
        c = self.creep
        state = (self.commits, c.version)
        if self._offset_cache is None or self._offset_cache[0] != state:
            self._offset_cache = (state, {}, {})
        _, known, means = self._offset_cache
        t = float(t)
        if t in known:
            return known[t][0].copy()
        if t not in means:
            if len(means) >= 16:
                means.clear()
            memo = self._propagated.get((self.commits, t))
            if memo is not None:
                tau, x = memo[0], memo[2]
            else:
                tau, dt = self._relative(t)
                F = transition(dt)
                if self.statics:          # as _predict's: the static parameters stay
                    F = np.eye(STATE_DIM + self.statics)
                    F[:STATE_DIM, :STATE_DIM] = transition(dt)
                x = F @ self._x
            means[t] = self._rows(np.eye(2), None, tau) @ x + c.offset(tau)
        return means[t].copy()

    def r_max(self, t: float, k: float = 3.0) -> float:
        """Largest expected drift error radius (nm) at ``t``: ``k √λ_max`` of the offset
        covariance. The executor sizes local scan lines with it (``l > R + r_max``)."""
        number("k", k, nonnegative=True)
        cov = self.offset(t).cov
        return float(k * math.sqrt(max(float(np.linalg.eigvalsh(cov)[-1]), 0.0)))

    def inflate(self, offset_std: float = 0.0, velocity_std: float = 0.0) -> None:
        """Add independent uncertainty (nm, nm/s) to the current estimate, e.g. after
        the executor decides the drift jumped (several lone measurements gated out)."""
        number("offset_std", offset_std, nonnegative=True)
        number("velocity_std", velocity_std, nonnegative=True)
        extra = np.diag([offset_std] * 2 + [velocity_std] * 2 + [0.0] * self.statics)
        L = tria(np.hstack([self._L, extra]))
        self._commit(self._tau, 0.0, self._x, L, self._x, L, extra, "inflate")
        self._streak = []
        self._anchor = (len(self.history) - 1, self._tau)

    # -- inputs ---------------------------------------------------------------------------
    def record_move(self, t: float, step) -> bool:
        """Register a scanner move by ``step`` (nm, (2,)) completed at ``t`` (s).

        With ``creep.tau_std``, a move that creeps widens the offset along its step by
        ``c |s| tau_std / ln 10`` (the lasting offset an error of the time constant leaves,
        e.g. 8.7 nm for 10 µm at c = 0.01, tau_std = 0.2), at the filter's present time:
        the next reference places it. Returns whether it is long enough to creep
        (``creep.min_step``).
        """
        return self.record_moves([t], [step]) == 1

    def record_moves(self, times, steps) -> int:
        """Register the pieces of one motion (:meth:`record_move` each, in time order).
        The lasting offset of a time-constant error is common to them, so the estimate
        widens once, by the sum of the pieces kept. Returns how many were kept."""
        kept = np.zeros(2)
        n = 0
        for t, step in zip(times, steps):
            tau, _ = self._relative(t)
            if self.creep.record(tau, step):
                kept += np.asarray(step, float).reshape(2)
                n += 1
        c, sd = self.params.creep.amplitude, self.params.creep.tau_std
        if n and c > 0 and sd > 0 and self.tau_static is None:
            g = np.zeros((self._x.shape[0], 1))
            g[:2, 0] = kept * (c * sd / math.log(10.0))
            L = tria(np.hstack([self._L, g]))
            self._commit(self._tau, 0.0, self._x, L, self._x, L, self._noise_sqrt(0.0), "move")
        return n

    def measure(self, t: float, z, R=None, *, label: str | None = None) -> Measurement:
        """Fold one measured offset ``z`` (nm, (2,)) at ``t`` into the estimate, unless the
        χ² gate rejects it (then the estimate is only predicted to ``t``).

        Parameters
        ----------
        t : float
            Time of the measurement (s), not before :attr:`time`.
        z : (2,) array
            Measured position in the scanner frame minus believed layout position (nm).
        R : (2, 2) array, optional
            Its covariance (nm²); ``measurement_std² I`` by default.
        label : str, optional
            The object's or landmark's name: kept in the log, and consecutive rejections
            count as agreeing objects only when their labels differ.
        """
        return self.measure_many(t, [z], None if R is None else [R],
                                 labels=None if label is None else [label]).results[0]

    def measure_many(self, t: float, zs, Rs=None, *, labels=None) -> JointMeasurement:
        """Fold several offsets measured at ``t`` (objects and landmarks) jointly.

        Parameters
        ----------
        t : float
            Time (s), not before :attr:`time`.
        zs : (n, 2) array
            Measured offsets (nm).
        Rs : (n, 2, 2) array, optional
            Their covariances (nm²); ``measurement_std² I`` each by default.
        labels : sequence of n str, optional

        Returns
        -------
        JointMeasurement
            Rejected objects have ``accepted=False``: treat them as moved. When
            ``readmitted`` is not empty, the objects of those earlier rejections did not
            move after all: the drift had jumped.
        """
        if self.statics:
            raise ValueError("a filter with static parameters measures through measure_projected")
        batch = self._batch(t, zs, Rs, labels)
        dt = batch.tau - self._tau
        folded = fold(self.params, self._x, self._L, dt, batch, None)
        if not folded.sel.accepted.any():
            recovered = self._recover(batch)
            if recovered is not None:
                return recovered
            self._streak.append(batch)
        self._commit_fold(batch, dt, folded)
        if folded.sel.accepted.any():
            self._streak = []
            self._anchor = (len(self.history) - 1, batch.tau)
        self.measurements.extend(folded.results)
        return JointMeasurement(batch.t, folded.results, folded.sel.joint_nis, folded.sel.dof,
                                folded.sel.drift_jump)

    def measure_projected(self, t: float, z, directions, R=None, *, label: str | None = None,
                          static=None) -> Measurement:
        """Fold components of the offset measured along unit ``directions`` at ``t``: a
        fixed feature's straight edge measures only the coordinate normal to it
        (``z_k = directions_k · offset + noise``). Gated alone (χ² with ``m`` dof); a
        rejection only predicts the estimate to ``t`` and takes no part in drift-jump
        recovery (the caller decides what a fixed feature out of place means).

        Parameters
        ----------
        t : float
            Time (s), not before :attr:`time`.
        z : (m,) array
            Measured components (nm), creep included.
        directions : (m, 2) array
            Unit vectors.
        R : (m, m) array, optional
            Covariance of ``z`` (nm²); ``measurement_std² I`` by default.
        label : str, optional
        static : (m, statics) array, optional
            How ``z`` depends on the static parameters too (``z = N offset + static θ``),
            e.g. the drift a reference image carried; none by default. With
            ``learn_creep``, ``statics`` counts the user's alone, or one more: the last
            column is a dependence on the creep amplitude's error beyond the creep now.
        """
        N = np.asarray(directions, float).reshape(-1, 2)
        z = np.asarray(z, float).reshape(-1)
        m = N.shape[0]
        if m == 0 or z.shape != (m,) or not (np.all(np.isfinite(z)) and np.all(np.isfinite(N))):
            raise ValueError(f"z and directions must be finite, shapes (m,) and (m, 2), got {z.shape}, {N.shape}")
        if not np.allclose(np.hypot(N[:, 0], N[:, 1]), 1.0, atol=1e-9):
            raise ValueError("directions must be unit vectors")
        R = np.eye(m) * self.params.measurement_std**2 if R is None else np.asarray(R, float)
        if R.shape != (m, m) or not (np.all(np.isfinite(R)) and np.allclose(R, R.T)
                                     and np.linalg.eigvalsh(R)[0] > 0):
            raise ValueError(f"R must be a symmetric positive definite ({m}, {m}) array")
        tau, dt = self._relative(t)
        p = self.params
        self.creep.prune(tau)
        creep, creep_sqrt = self.creep.offset(tau), self.creep.cov_sqrt(tau)
        H = self._rows(N, static, tau)
        x_prior, L_prior = self._predict(self._x, self._L, dt)
        Q_sqrt = self._noise_sqrt(dt)
        NC = N @ creep_sqrt
        R_total = symmetrize(R + NC @ NC.T)
        thermal = z - N @ creep
        prior_sqrt = tria(np.hstack([H @ L_prior, NC]))
        S_sqrt = tria(np.hstack([prior_sqrt, np.linalg.cholesky(R)]))
        innovation = thermal - H @ x_prior
        score, threshold = nis_sqrt(innovation, S_sqrt), gate_threshold(m, p.gate_probability)
        ok = score <= threshold
        if ok:
            x, L = sqrt_update_core(x_prior, L_prior, thermal, np.linalg.cholesky(R_total), H)[:2]
        else:
            x, L = x_prior, L_prior
        self._commit(tau, dt, x, L, x_prior, L_prior, Q_sqrt, "measure", creep, creep_sqrt)
        if ok:
            self._streak = []
            self._anchor = (len(self.history) - 1, tau)
        result = Measurement(self.epoch + tau, z.copy(), R.copy(), ok, "accepted" if ok else "gated",
                             score, threshold, innovation, gram(S_sqrt), label, directions=N.copy())
        self.measurements.append(result)
        return result

    def projected(self, t: float, directions, static=None) -> tuple[np.ndarray, np.ndarray]:
        """What :meth:`measure_projected` would expect at ``t``: the predicted components
        ``N offset + static θ`` (creep included) and their covariance (the creep
        amplitude's uncertainty included); the filter is unchanged."""
        N = np.asarray(directions, float).reshape(-1, 2)
        tau, _, x, L, _ = self._propagate(t)
        H = self._rows(N, static, tau)
        A = np.hstack([H @ L, N @ self.creep.cov_sqrt(tau)])
        return H @ x + N @ self.creep.offset(tau), gram(A)

    def _rows_many(self, N: np.ndarray, statics: np.ndarray, tau: float) -> np.ndarray:
        """:meth:`_rows` for each of ``statics`` ((K, m, statics)), (K, m, n): the
        same sums, taken at once."""
        user = self.statics - int(self.learn_creep)
        S = np.asarray(statics, float)
        if S.ndim != 3 or S.shape[1:] not in ((N.shape[0], user), (N.shape[0], user + 1)) \
                or not np.all(np.isfinite(S)):
            raise ValueError(f"statics must be a finite (K, {N.shape[0]}, {user}) array")
        H = np.repeat(self._rows(N, None, tau)[None], S.shape[0], axis=0)
        H[:, :, STATE_DIM:STATE_DIM + user] += S[:, :, :user]
        if self.learn_creep and S.shape[2] == user + 1:
            H[:, :, -1] += S[:, :, user]
        return H

    def weigh_many(self, t: float, directions, R, statics) -> tuple[np.ndarray, np.ndarray]:
        """For each of ``statics`` ((K, m, statics)) at once, predicted at ``t`` once:
        :meth:`projected`'s covariance (K, m, m) and :meth:`information` with ``R`` (K,),
        by the same sums (choosing among a thousand references)."""
        N = np.asarray(directions, float).reshape(-1, 2)
        tau, _, x, L, _ = self._propagate(t)
        H = self._rows_many(N, statics, tau)
        Ht = np.swapaxes(H, 1, 2)
        cc = N @ self.creep.cov_sqrt(tau)
        A = np.concatenate([H @ L, np.broadcast_to(cc, (H.shape[0], *cc.shape))], axis=2)
        O = self._rows(np.eye(2), None, tau)
        P = gram(L)
        S = H @ P @ Ht + cc @ cc.T + np.asarray(R, float)
        cross = O @ P @ Ht + self.creep.cov_sqrt(tau) @ cc.T
        gains = np.einsum("kij,kij->k", cross, np.swapaxes(np.linalg.solve(S, np.swapaxes(cross, 1, 2)), 1, 2))
        return symmetrize(A @ np.swapaxes(A, 1, 2)), gains

    def information(self, t: float, directions, R, static=None) -> float:
        """How much measuring ``N offset + static θ`` at ``t`` with covariance ``R``
        would shrink the offset's uncertainty there: the reduction of its covariance's
        trace (nm²); the filter is unchanged."""
        N = np.asarray(directions, float).reshape(-1, 2)
        tau, _, x, L, _ = self._propagate(t)
        H = self._rows(N, static, tau)
        O = self._rows(np.eye(2), None, tau)
        cc = N @ self.creep.cov_sqrt(tau)
        P = gram(L)
        S = H @ P @ H.T + cc @ cc.T + np.asarray(R, float)
        cross = O @ P @ H.T + self.creep.cov_sqrt(tau) @ cc.T
        return float(np.trace(cross @ np.linalg.solve(S, cross.T)))

    def forget_offset(self, t: float, std: float) -> None:
        """Forget where the offset was (a drift jump, a long pause): predicted to ``t``, its
        standard deviation becomes ``std`` (nm) per axis, uncorrelated with the velocity
        and the static parameters, which are kept; the next measurement places it."""
        number("std", std, positive=True)
        tau, dt = self._relative(t)
        x, L = self._predict(self._x, self._L, dt)
        P = gram(L)
        P[:2, :] = 0.0
        P[:, :2] = 0.0
        P[:2, :2] = np.eye(2) * std**2
        self._commit(tau, dt, x, psd_sqrt(P), x, L, self._noise_sqrt(dt), "reset")
        self._streak = []
        self._anchor = (len(self.history) - 1, tau)

    def reinitialise(self, t: float, offset, cov, *, velocity_std: float = 0.0) -> None:
        """Start the offset afresh at ``t`` from an absolute measurement (``offset`` nm,
        creep included, with covariance ``cov``, e.g. a relocalisation by image
        registration): the velocity estimate is kept, its uncertainty widened by
        ``velocity_std`` (nm/s); the offset forgets its past and its correlation with
        the velocity."""
        offset = np.asarray(offset, float).reshape(2)
        cov = np.asarray(cov, float)
        number("velocity_std", velocity_std, nonnegative=True)
        if not (np.all(np.isfinite(offset)) and cov.shape == (2, 2) and np.all(np.isfinite(cov))
                and np.allclose(cov, cov.T) and np.linalg.eigvalsh(cov)[0] > 0):
            raise ValueError("offset must be finite (2,) and cov symmetric positive definite (2, 2)")
        tau, dt = self._relative(t)
        self.creep.prune(tau)
        x_prior, L_prior = self._predict(self._x, self._L, dt)
        x = x_prior.copy()
        x[:2] = offset - self.creep.offset(tau)
        P = gram(L_prior)
        P[:2, :] = 0.0
        P[:, :2] = 0.0
        P[:2, :2] = cov
        P[2:4, 2:4] += np.eye(2) * velocity_std**2
        self._commit(tau, dt, x, psd_sqrt(P), x_prior, L_prior, self._noise_sqrt(dt), "reset")
        self._streak = []
        self._anchor = (len(self.history) - 1, tau)

    def _batch(self, t, zs, Rs, labels) -> Batch:
        zs = np.asarray(zs, float).reshape(-1, 2)
        n = zs.shape[0]
        if n == 0 or not np.all(np.isfinite(zs)):
            raise ValueError("zs must hold at least one finite (2,) offset")
        if Rs is None:
            Rs = np.broadcast_to(np.eye(2) * self.params.measurement_std**2, (n, 2, 2))
        Rs = np.asarray(Rs, float).reshape(n, 2, 2)
        if not np.all(np.isfinite(Rs)):
            raise ValueError("Rs must be finite")
        for i, R in enumerate(Rs):
            if not (np.allclose(R, R.T) and np.linalg.eigvalsh(R)[0] > 0):
                raise ValueError(f"Rs[{i}] must be symmetric positive definite")
        labels = (None,) * n if labels is None else tuple(labels)
        if len(labels) != n:
            raise ValueError(f"labels must have {n} entries, got {len(labels)}")
        tau, _ = self._relative(t)
        self.creep.prune(tau)
        creep = self.creep.offset(tau)
        creep_sqrt = self.creep.cov_sqrt(tau)
        return Batch(tau, self.epoch + tau, zs.copy(), zs - creep, Rs.copy(), creep, creep_sqrt,
                      labels)

    def _commit_fold(self, batch: Batch, dt: float, folded: Folded) -> None:
        self._commit(batch.tau, dt, folded.x, folded.L, folded.x_prior, folded.L_prior,
                     folded.Q_sqrt, "measure", batch.creep, batch.creep_sqrt)

    def _recover(self, batch: Batch) -> JointMeasurement | None:
        """Re-run the streak of rejected batches from the last accepted state with the
        prior widened by the first one's innovation (an offset jump, or the velocity
        error that would produce it); adopt it when it accepts every measurement."""
        p = self.params
        streak = [*self._streak, batch]
        labels = [lab for b in streak for lab in b.labels]
        distinct = len({lab for lab in labels if lab is not None}) + labels.count(None)
        if p.min_consensus == 0 or distinct < max(2, p.min_consensus):
            return None
        index, tau = self._anchor
        x, L = self.history[index].x, self.history[index].P_sqrt
        first = streak[0]
        x_first = predict_sqrt(x, L, first.tau - tau, p.q, p.q_offset)[0]
        e = weighted_mean(first.thermal, first.Rs)[0] - x_first[:2]
        widen = np.zeros((STATE_DIM, 2))
        widen[:2, 0] = e
        if first.tau > tau:
            widen[2:, 1] = e / (first.tau - tau)
        folds = []
        for j, b in enumerate(streak):
            f = fold(p, x, L, b.tau - tau, b, widen if j == 0 else None)
            if not f.sel.accepted.all():
                return None
            folds.append(f)
            x, L, tau = f.x, f.L, b.tau
        del self.history[index + 1:]
        _, self._tau = self._anchor
        for j, (b, f) in enumerate(zip(streak, folds)):
            self._commit_fold(b, b.tau - (self._anchor[1] if j == 0 else streak[j - 1].tau), f)
        self._streak = []
        self._anchor = (len(self.history) - 1, batch.tau)
        jumped = [tuple(replace(r, drift_jump=True) for r in f.results) for f in folds]
        readmitted = tuple(r for rs in jumped[:-1] for r in rs)
        self.measurements.extend(readmitted + jumped[-1])
        last = folds[-1].sel
        return JointMeasurement(batch.t, jumped[-1], last.joint_nis, last.dof, True, readmitted)
