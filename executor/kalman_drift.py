"""The drift estimator of the kalman and full strategies: the drift filter of
:mod:`nanoasm.drift`, its references, the creep of every recorded scanner move, and when
the estimate can no longer be trusted (relocalisation).

References are of two kinds, chosen by information per second
(:mod:`.reference_choice`): objects never pushed, measured against where the first
full scan saw them, and fixed features of the obstacles (:mod:`.landmarks`), which
never move and so never run out. An object a push came near is quarantined
(:mod:`.references`) until a scan finds it where it should be.

The estimate is relocalised (:mod:`.relocalise`) when its uncertainty passes
``relocalise_sigma``, when references are rejected ``relocalise_rejections`` times in a
row (the drift jumped, or everything near moved), or after a resume that stood still
for ``relocalise_pause``.
"""

from __future__ import annotations

import math

import numpy as np

from nanoasm.drift import DriftFilter, DriftFilterParams, gate_threshold
from nanoasm.drift.creep import CreepingOffset, CreepModelParams

from . import creep_terms
from .reference_choice import Candidate, best_reference
from .references import References
from .scan_drift import EPS, LAM, PARAMETERS, ScanDrift, filter_theta
from .scan_jump import against_torn_scan
from .strategy import ExecOptions
from .trust import Trust

#: Variance (nm² per axis) of an object's position in the first full scan, its row's
#: drift aside (identification measured 0.28 nm on centres; 2 nm covers pixel effects).
FULL_SCAN_VAR = 4.0
#: Static parameters of the filter's state after the bootstrap: the full scan's drift
#: model θ (velocity and its steady change, :class:`~nanoasm.executor.scan_drift.ScanDrift`).
SCAN_STATICS = 4                 # θ's thermal part; ε rides in the filter's learnt creep


def filter_params(options: ExecOptions) -> DriftFilterParams:
    """The drift filter's parameters for a run's options: the nominal creep, with the
    uncertainty of its amplitude (a real scanner's creep is known to about ±30 %)."""
    creep = CreepModelParams(amplitude_std=options.creep_amplitude_std, tau_std=options.creep_tau_std)
    return DriftFilterParams(q=options.drift_q, q_offset=options.drift_q_offset, offset_std=1.0, creep=creep)


class Kalman:
    """Kalman and full: the drift filter, its references and the creep of the moves."""

    references_are_objects = emits = bootstraps = uses_landmarks = True

    def __init__(self, origin, epoch: float, options: ExecOptions):
        self.origin = np.asarray(origin, float)
        self.epoch = float(epoch)
        self.params = filter_params(options)
        self.filter = DriftFilter(self.params, epoch=self.epoch)
        self.move_log: list[tuple[float, np.ndarray]] = []   # replayed when restarted
        self.creep_anchor: np.ndarray | None = None   # where the last recorded move ended, nm
        self.trust = Trust()                          # references rejected in a row, relocalisations
        self._scan_theta = None                       # (filter, its commits, θ, cov) as last read
        # the drift the full scan's rows carried (the filter's own velocity follows the
        # drift as it changes later)
        c = self.params.creep
        self.scan = ScanDrift(self.epoch, self.params.velocity_std, c.amplitude, c.tau,
                              creep_std=c.amplitude_std, tau_std=c.tau_std)

    @property
    def velocity_known(self) -> bool:
        """Whether the bootstrap has measured the velocity in every direction."""
        return self.scan.known

    def restart(self, t: float) -> None:
        """Start the filter afresh at the end of the bootstrap (instrument time ``t``) from
        what the full scan's skew gave: the offset then (the model's drift at ``t``), the
        velocity then, and the model's parameters ``θ`` themselves, kept in the filter's
        state as static parameters, so that every reference measured against the full
        scan refines them and their errors are never taken for independent noise; the
        moves recorded so far are its creep input, whose amplitude it learns too (a real
        scanner's is known to some ±30 %), and its time constant's error ``λ`` (a static
        whose effect the filter adds itself, every move's)."""
        tau = t - self.epoch
        k, c = SCAN_STATICS, self.params.creep.amplitude
        # state: thermal offset and velocity at τ, θ's thermal part, λ, the creep
        # amplitude's error c ε (the filter's creep term carries ε for every move, the scan's too)
        M = np.vstack([self.scan.thermal_jacobian(tau), self.scan.velocity_jacobian(tau),
                       np.eye(k, PARAMETERS), np.eye(1, PARAMETERS, LAM), np.eye(1, PARAMETERS, EPS) * c])
        x0, P0 = self.scan.mapped(M)          # a jump since the full scan: the offset carries it
        P0[:2, :2] += np.eye(2) * 4.0
        P0[2:4, 2:4] += np.eye(2) * 1e-6
        revision = self.filter.revision           # a new filter: one revision more, not a count afresh
        self.filter = DriftFilter(self.params, epoch=self.epoch, x0=x0, P0=0.5 * (P0 + P0.T), statics=k + 1,
                                  start=tau, learn_creep=True, tau_static=k)
        self.filter.revision = revision + 1
        for t_move, step in self.move_log:
            self.filter.creep.record(t_move - self.epoch, step)

    def scan_theta(self) -> tuple[np.ndarray, np.ndarray]:
        """The full scan's drift model ``θ`` and its covariance: the filter's once it
        holds them (after the bootstrap), the bootstrap's before."""
        if self.filter.statics:
            f, kept = self.filter, self._scan_theta          # kept while the filter's state stands
            if kept is None or kept[0] is not f or kept[1] != f.commits:
                kept = self._scan_theta = (f, f.commits, *filter_theta(f, SCAN_STATICS, self.params.creep.amplitude))
            return kept[2].copy(), kept[3].copy()
        return self.scan.theta, self.scan.cov

    def static_rows(self, normals, taus) -> np.ndarray:
        """How components measured against the full scan depend on the filter's statics
        ``θ`` (``λ`` among them) and its creep amplitude error ``c ε``: ``-n_k J(τ_k)``,
        ``ε``'s column per ``c`` (the filter adds λ's effect now itself)."""
        cols = [*range(SCAN_STATICS), *([LAM] if self.filter.tau_static is not None else []), EPS]
        J = np.array([-np.asarray(n, float) @ self.scan.jacobian(tau)[:, cols] for n, tau in zip(normals, taus)])
        J[:, -1] /= self.params.creep.amplitude
        return J

    # -- the estimate ---------------------------------------------------------------------
    def _bootstrapping(self) -> bool:
        """Between the full scan's end and the filter's start: the scan's drift model estimates."""
        return self.scan.ended and not self.filter.statics

    def offset(self, t: float) -> np.ndarray:
        if self._bootstrapping():
            tau, theta = t - self.epoch, self.scan.theta
            return (self.origin + self.scan.thermal_jacobian(tau) @ theta
                    + (1.0 + theta[EPS]) * self.filter.creep.offset(tau)
                    + theta[LAM] * self.filter.creep.tau_sensitivity(tau) + self.scan.step(tau))
        return self.origin + self.filter.offset_mean(t)

    def revision(self) -> object:
        """Equal to an earlier token while no measurement or reset revised the estimate."""
        return [self._bootstrapping(), self.filter.revision]

    def offset_cov(self, t: float) -> np.ndarray:
        """Covariance (nm²) of :meth:`offset` at ``t`` (creep's uncertainty included)."""
        if self._bootstrapping():
            return self.scan.offset_cov(t - self.epoch) + self.filter.creep.cov(t - self.epoch)
        return np.asarray(self.filter.offset(self.clamp(t)).cov, float)

    def compensation(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
        """The creep within ``offset(t1) - offset(t0)`` and the covariance of that
        difference's error (:func:`.creep_terms.compensation`)."""
        return creep_terms.compensation(self, t0, t1)

    def sigma(self, t: float) -> float:
        """Standard deviation (nm) of the offset along its worst direction at ``t``."""
        return math.sqrt(max(float(np.linalg.eigvalsh(self.offset_cov(t))[-1]), 0.0))

    def velocity(self) -> np.ndarray:
        return np.asarray(self.filter.x[2:4], float)

    def velocity_std(self) -> float:
        """Standard deviation of the velocity estimate's x component, nm/s."""
        return math.sqrt(self.filter.P[2, 2])

    def creep_offset(self, tau: float) -> np.ndarray:
        """The offset the recorded moves' creep is modelled to cause ``tau`` s after the epoch."""
        return self.filter.creep.offset(tau)

    def full_scan_done(self, t: float | None = None) -> None:
        """The full scan has ended (at instrument time ``t``, if given: a jump of the drift
        after it can then be told): the moves so far are the ones whose creep its rows
        carried."""
        self.scan.scan_ended(self.move_log, None if t is None else t - self.epoch)

    def unskew(self, at: np.ndarray, tau) -> np.ndarray:
        """A full-scan position seen ``tau`` s after the epoch, its row's drift taken out
        (:class:`~nanoasm.executor.scan_drift.ScanDrift`, with ``θ`` as now known); or
        positions ``(n, 2)`` seen at times ``tau`` ``(n,)``, each to the bit the one's."""
        theta, _ = self.scan_theta()
        if np.ndim(tau):        # a belief's thousand positions, in one product
            J = np.array([self.scan.jacobian(t) for t in tau]).reshape(-1, 2, theta.size)
            return at - J @ theta - J[:, :, EPS] - np.array([self.scan.step(t) for t in tau]).reshape(-1, 2)
        return at - self.scan.jacobian(tau) @ theta - self.scan.creep_at(tau) - self.scan.step(tau)

    def skew_cov(self, tau: float) -> np.ndarray:
        """Covariance (nm²) that :meth:`unskew` carries through ``θ``'s uncertainty."""
        J = self.scan.jacobian(tau)
        return J @ self.scan_theta()[1] @ J.T

    def full_scan_cov(self, t: float, tau: float) -> np.ndarray:
        """Covariance (nm²) of where a point the full scan saw at ``τ`` lies in the
        scanner frame at ``t``: the offset then less the row's drift, correlated as the
        filter knows them; before the bootstrap, the drift model's between the two."""
        if not self.filter.statics:
            return self.scan.between_cov(t - self.epoch, tau)
        t = self.clamp(t)
        return self.filter.projected(t, np.eye(2), self.static_rows(np.eye(2), [tau, tau]))[1]

    def radius(self, t: float, seen, skew_tau: float | None, options: ExecOptions, full_scan=None) -> float:
        """3σ error of a believed position: the sighting's and, for a position known from the
        full scan alone, where that row's point is now (``full_scan``: its :meth:`full_scan_cov`,
        if known); else the offset's."""
        cov = np.zeros((2, 2)) if seen is None else np.asarray(seen.cov, float)
        if seen is not None and skew_tau is not None:
            cov = cov + (self.full_scan_cov(t, skew_tau) if full_scan is None else full_scan)
        else:
            cov = cov + self.offset_cov(t)
        return 3.0 * math.sqrt(max(float(np.linalg.eigvalsh(cov)[-1]), 0.0))

    def information(self, t: float, normals, static, R) -> float:
        """Reduction (nm²) of the offset covariance's trace at ``t`` by measuring the
        components ``normals · offset + static θ`` with covariance ``R``."""
        return self.filter.information(self.clamp(t), normals, R, static if self.filter.statics else None)

    def observation_cov(self, t: float, cov) -> np.ndarray:
        """A measured pose's covariance in the layout frame: the drift estimate's added."""
        return np.asarray(cov, float) + self.offset_cov(t)

    def clamp(self, t: float) -> float:
        return max(t, self.filter.time)

    def doc(self, t: float) -> dict:
        t = self.clamp(t)
        off = self.offset(t) - self.origin
        return {"t": t, "offset": [float(off[0]), float(off[1])],
                "cov": np.asarray(self.filter.offset(t).cov, float).tolist(),
                "velocity": [float(v) for v in self.filter.x[2:4]]}

    # -- references -----------------------------------------------------------------------
    def after_plan(self, plan, belief, area) -> None:
        """The first plan is made: its references are chosen push by push."""

    def wants_reference(self, t: float, options: ExecOptions) -> bool:
        """Whether a reference is due before a push at ``t``: none yet, the last update
        older than ``reference_every``, or the offset's σ above ``reference_sigma``."""
        f = self.filter
        return (not (f.measurements or f.resumed_measurements) or t - f.time >= options.reference_every
                or self.sigma(t) > options.reference_sigma)

    def reference_target(self, ctx, t: float, near, obj_id, *, force: bool = False) -> Candidate | None:
        """The reference to scan before a push of ``obj_id`` near ``near`` (None: not due,
        unless ``force``, or none left): of the untouched particles and the fixed features,
        the one of most information per second; not one the present streak rejected (out
        of place again, it tells nothing new: a missed feature is not retired at once)."""
        if not (force or self.wants_reference(t, ctx.options)):
            return None
        return best_reference(ctx, self, t, FULL_SCAN_VAR, ctx.landmarks.candidates(ctx, self, t),
                              self.trust.rejected)

    def _consistent(self, t: float, z: np.ndarray, static: np.ndarray, R: np.ndarray) -> bool:
        """Whether an offset measured at ``t`` against the full scan agrees with the
        estimate (the χ² gate), without folding it in."""
        mean, cov = self.filter.projected(self.clamp(t), np.eye(2), static)
        nu = z - mean
        return float(nu @ np.linalg.solve(cov + R, nu)) <= gate_threshold(2, self.params.gate_probability)

    def measure(self, obj_id, at, cov, t, refs, pushed, lost, creep_sens=None) -> bool | None:
        """Fold a reference's measured position (scanner frame) into the filter, against
        where the full scan saw it (its row's drift a part of the filter's state): None if
        it is no reference, else whether it agreed. A rejected one moved on its own and
        is no reference from then on; a quarantined one is only checked (re-validated
        when it agrees). ``creep_sens``: how the located position moves per unit relative
        error of the creep amplitude its scan lines were compensated with."""
        if not refs.is_reference(obj_id, pushed, lost):
            return None
        raw, seen_t = refs.first_seen[obj_id]
        tau = seen_t - self.epoch
        z = np.asarray(at) - self.origin - raw + self.scan.creep_at(tau)
        static = self.static_rows(np.eye(2), [tau, tau])
        z, static = creep_terms.with_creep(self, z, static, creep_sens)
        R = np.asarray(cov, float) + np.eye(2) * FULL_SCAN_VAR
        z, R = against_torn_scan(self.scan, z, R, np.eye(2), [tau, tau])
        ref = self.unskew(raw, tau)
        if obj_id in refs.quarantine:
            if self._consistent(t, z, static, R):
                refs.revalidate(obj_id)
                return True
            refs.moved(obj_id, ref, seen_t)
            return False
        if self.filter.measure_projected(self.clamp(t), z, np.eye(2), R, label=obj_id, static=static).accepted:
            self.trust.accept(t)
            return True
        refs.moved(obj_id, ref, seen_t)
        self.reject(obj_id, t)
        return False

    def measure_reference(self, obj_id, at, cov, t, refs, pushed, lost, creep_sens=None) -> bool | None:
        return self.measure(obj_id, at, cov, t, refs, pushed, lost, creep_sens)

    def measure_feature(self, feature_id: str, z, H, R, t: float, taus=None, creep_sens=None) -> bool:
        """Fold a fixed feature's measured offset components ``z`` along the rows of
        ``H`` (layout frame, nm; covariance ``R``), each against where the full scan saw
        its site at ``taus`` (s after the epoch; ``creep_sens`` as for :meth:`measure`,
        one a row); whether the gate accepted it."""
        static = None if taus is None else self.static_rows(H, taus)
        z, R = (z, R) if taus is None else against_torn_scan(self.scan, z, R, H, taus)
        z, static = creep_terms.with_creep(self, z, static, creep_sens)
        m = self.filter.measure_projected(self.clamp(t), z, H, R, label=feature_id, static=static)
        if m.accepted:
            self.trust.accept(t)
        else:
            self.reject(feature_id, t)
        return m.accepted

    def reject(self, label: str, t: float) -> None:
        """A reference was rejected, or not found where it should be, at ``t``."""
        self.trust.reject(label, t)

    # -- relocalisation (when: :class:`~nanoasm.executor.trust.Trust`) ---------------------
    def needs_relocalisation(self, t: float, options: ExecOptions) -> tuple[str, str] | None:
        """Why the estimate must be relocalised before going on (:meth:`Trust.needs`)."""
        return self.trust.needs(t, self.sigma(t), options)

    def resumed(self, pause: float) -> None:
        """The run resumes after standing still ``pause`` s."""
        self.trust.pause = float(pause)

    def relocalised(self, t: float, z, R, tau: float, refs: References) -> list[str]:
        """Start the offset afresh at ``t`` from a registration: ``z`` (nm) is the drift
        since the epoch less the full scan's at ``tau``, covariance ``R``. The references
        rejected in the streak that led here are re-admitted (and returned)."""
        t = self.clamp(t)
        self.filter.forget_offset(t, 1e4)
        z = np.asarray(z, float) + self.scan.step(tau)    # a window on rows a jump tore the scan at
        self.filter.measure_projected(t, z, np.eye(2), R, label="relocalisation",
                                      static=self.static_rows(np.eye(2), [tau, tau]))
        forgiven = self.trust.relocalised(t)
        for label in forgiven:
            refs.gated.discard(label)
        return forgiven

    def relocalise_failed(self, t: float) -> None:
        """No window registered at ``t``: go on as before, without retrying for a while."""
        self.trust.failed(t)

    # -- creep ----------------------------------------------------------------------------
    def moved_to(self, xy, t: float, start=None) -> None:
        """The scanner reached ``xy`` (nm) at ``t``: creep follows the step from where the
        last recorded move ended. A step shorter than the creep model's ``min_step`` is
        not recorded and does not restart the chain, so its displacement is carried into
        the next move: every displacement creeps, only its time is coarsened."""
        xy = np.asarray(xy, float)
        if self.creep_anchor is None:
            self.creep_anchor = np.asarray(xy if start is None else start, float)
        step = xy - self.creep_anchor
        if math.hypot(*step) >= self.filter.params.creep.min_step:
            t = max(t, self.filter.time)
            step = np.asarray(step, float)
            self.move_log.append((t, step))
            self.filter.record_move(t, step)
            self.creep_anchor = xy

    def moved_along(self, xy, t, start=None, rests=()) -> None:
        """The scanner went through the points ``xy`` ((n, 2) nm) at times ``t`` ((n,) s),
        coming to rest at the indices ``rests``: the moves the instrument's creep follows
        (:func:`~nanoasm.drift.creep.creep_moves`: pieces as it goes, and ends where it
        stops) are recorded, each creeping from its own time."""
        xy = np.asarray(xy, float).reshape(-1, 2)
        if self.creep_anchor is None and len(xy):
            self.creep_anchor = np.asarray(xy[0] if start is None else start, float)
        ks, steps = creep_terms.steps_along(self, self.creep_anchor, xy, t, rests)
        if ks.size:
            times = np.maximum.accumulate(np.maximum(np.asarray(t, float).reshape(-1)[ks], self.filter.time))
            self.move_log.extend(zip(times.tolist(), steps))
            self.filter.record_moves(times, steps)
            self.creep_anchor = xy[ks[-1]].copy()

    def pending_moves(self, dac, current, config) -> list:
        """The moves a streamed path will be recorded as (:meth:`moved_along`),
        ``[(t, step), ...]``; XY rests where the travel and the push end."""
        if not dac.n_samples:
            return []
        anchor = self.creep_anchor if self.creep_anchor is not None else config.codes_to_nm(np.asarray(current))[:2]
        samples = dac.render(np.arange(1, dac.n_samples + 1))
        ks, steps = creep_terms.steps_along(self, anchor, samples.nm[:, :2], samples.t,
                                            dac.profile.rests() - 1)
        return [(float(samples.t[k]), step) for k, step in zip(ks, steps)]

    def creep_scale(self) -> float:
        """The creep amplitude as learnt over the nominal one, ``(c + δc) / c``."""
        f, c = self.filter, self.params.creep.amplitude
        return 1.0 + float(f.x[-1]) / c if f.learn_creep and c > 0 else 1.0

    def predicted(self, t0: float, pending=()):
        """Thermal drift and the creep of the recorded and ``pending`` moves from ``t0``,
        at the creep amplitude learnt so far."""
        k = self.creep_scale()
        thermal = self.offset(t0) - k * self.creep_offset(t0 - self.epoch)
        return CreepingOffset(thermal, self.velocity(), t0, self.filter.creep, self.epoch, pending, scale=k)

    # -- checkpoints ----------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"kind": "kalman", "origin": [float(v) for v in self.origin], "epoch": self.epoch,
                "filter": self.filter.state_dict(),
                "creep_anchor": None if self.creep_anchor is None else [float(v) for v in self.creep_anchor],
                **self.trust.state_dict(), "scan": self.scan.state_dict()}

    @classmethod
    def from_state(cls, state: dict, options: ExecOptions) -> Kalman:
        out = cls(state["origin"], state["epoch"], options)
        out.scan = ScanDrift.from_state(state["scan"])
        out.filter = DriftFilter.from_state(out.params, state["filter"])
        out.creep_anchor = None if state["creep_anchor"] is None else np.asarray(state["creep_anchor"], float)
        out.trust = Trust.from_state(state)
        return out


__all__ = ["FULL_SCAN_VAR", "Kalman", "filter_params"]
