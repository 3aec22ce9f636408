"""Drift estimators: where the layout's origin lies in the scanner frame, and how well that
is known, for each way a run handles drift.

A strategy picks one (:func:`estimator_for`):

* :class:`NoDrift` (open-loop, local-scan): the origin stays where the run started;
  a believed position is off by at most ``r_max`` plus ``max_drift_rate`` times the
  time since the object was last seen.
* :class:`Anchor` (anchor): one fixed particle, scanned before every push, gives the
  offset directly.
* :class:`Kalman` (kalman, full): the drift filter of :mod:`nanoasm.drift`, fed by
  objects never pushed (measured against their full-scan position), with the creep of
  every recorded scanner move.

Each is plain state with ``state_dict()``/``from_state()``; scanning is the steps' job
(:mod:`nanoasm.executor.drift_steps`), which ask an estimator what to measure and tell it
what they found. Positions are nm, times instrument seconds.
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np

from nanoasm.drift import DriftFilter, DriftFilterParams
from nanoasm.drift.creep import CreepingOffset

from .dac_frames import LinearDrift
from .references import References
from .strategy import ExecOptions, Strategy

#: A drift reference is chosen at least this far (nm, plus a rod's length) from the push.
REFERENCE_GAP = 300.0
#: Variance (nm² per axis) of an object's position in the first full scan, its row's
#: drift aside (identification measured 0.28 nm on centres; 2 nm covers pixel effects).
FULL_SCAN_VAR = 4.0


class DriftEstimator(Protocol):
    """What a run asks of its drift handling (see the module docstring)."""

    origin: np.ndarray            # scanner position of the layout origin at the epoch, nm
    epoch: float                  # instrument time of the layout frame, s
    #: whether its references are ordinary objects of the belief (a sighting updates the
    #: belief, a reference not found is lost) rather than a feature held apart
    references_are_objects: bool
    #: whether a run emits its estimate on the drift topic after each update
    emits: bool
    #: whether it wants the drift velocity from the full scan's skew before planning
    bootstraps: bool

    def offset(self, t: float) -> np.ndarray: ...
    def velocity(self) -> np.ndarray: ...
    def unskew(self, at: np.ndarray, tau: float) -> np.ndarray: ...
    def radius(self, t: float, seen, skew_tau: float | None, options: ExecOptions) -> float: ...
    def observation_cov(self, t: float, cov) -> np.ndarray: ...
    def clamp(self, t: float) -> float: ...
    def doc(self, t: float) -> dict: ...
    def after_plan(self, plan, belief, area) -> None: ...
    def reference_target(self, t: float, near, obj_id, belief, refs: References, pushed,
                         moving, options: ExecOptions) -> str | None: ...
    def measure(self, obj_id: str, at, cov, t: float, refs: References, pushed, lost) -> bool | None: ...
    def measure_reference(self, obj_id: str, at, cov, t: float, refs: References, pushed,
                          lost) -> bool | None: ...
    def moved_to(self, xy, t: float, start=None) -> None: ...
    def pending_travel(self, dac, current, config) -> list: ...
    def predicted(self, t0: float, pending=()): ...
    def state_dict(self) -> dict: ...


class NoDrift:
    """Open-loop and local-scan: no drift is estimated; the origin stays put."""

    references_are_objects = False
    emits = False
    bootstraps = False

    def __init__(self, origin, epoch: float):
        self.origin = np.asarray(origin, float)
        self.epoch = float(epoch)
        self.drift = np.zeros(2)          # the estimated drift since the epoch, nm

    def offset(self, t: float) -> np.ndarray:
        """Scanner position of the layout's origin at ``t``."""
        return self.origin + self.drift

    def velocity(self) -> np.ndarray:
        return np.zeros(2)

    def unskew(self, at: np.ndarray, tau: float) -> np.ndarray:
        """A full-scan position with its row's drift taken out (none known here)."""
        return at

    def radius(self, t: float, seen, skew_tau: float | None, options: ExecOptions) -> float:
        """3σ error of a believed position last seen at ``seen`` (None: never): r_max plus
        the drift that can have built up at ``max_drift_rate`` since."""
        since = t - seen.t if seen is not None else 0.0
        return options.r_max + options.max_drift_rate * max(since, 0.0)

    def observation_cov(self, t: float, cov) -> np.ndarray:
        return np.asarray(cov, float)

    def clamp(self, t: float) -> float:
        return t

    def doc(self, t: float) -> dict:
        """The estimate at ``t``: offset since the start (nm), covariance, velocity."""
        off = self.offset(t) - self.origin
        return {"t": t, "offset": [float(off[0]), float(off[1])], "cov": None, "velocity": None}

    def after_plan(self, plan, belief, area) -> None:
        """The first plan is made (no drift reference to choose here)."""

    def reference_target(self, t, near, obj_id, belief, refs, pushed, moving, options) -> str | None:
        """The object to scan for drift before a push of ``obj_id`` near ``near`` (None here)."""
        return None

    def measure(self, obj_id, at, cov, t, refs, pushed, lost) -> bool | None:
        """Fold any located object's measured position (scanner frame) in: None (not
        used), True, or False (gated out)."""
        return None

    def measure_reference(self, obj_id, at, cov, t, refs, pushed, lost) -> bool | None:
        """Fold the measured position of the reference :meth:`reference_target` chose."""
        return None

    def moved_to(self, xy, t: float, start=None) -> None:
        """The scanner reached ``xy`` at ``t`` (creep is not modelled here)."""

    def pending_travel(self, dac, current, config) -> list:
        return []

    def predicted(self, t0: float, pending=()):
        """The origin's scanner offset as a function of time from ``t0`` (for the DAC)."""
        return LinearDrift(tuple(self.offset(t0)), (0.0, 0.0), t0)

    def state_dict(self) -> dict:
        return {"kind": "none", "origin": [float(v) for v in self.origin], "epoch": self.epoch,
                "drift": [float(v) for v in self.drift]}

    @classmethod
    def from_state(cls, state: dict, options: ExecOptions):
        out = cls(state["origin"], state["epoch"])
        out.drift = np.asarray(state["drift"], float)
        return out


class Anchor(NoDrift):
    """Anchor: one particle that no push moves, far from the action, located before every
    push; the offset is where it is found less where the full scan saw it."""

    emits = True

    def __init__(self, origin, epoch: float):
        super().__init__(origin, epoch)
        self.anchor: tuple[str, tuple[float, float]] | None = None

    def after_plan(self, plan, belief, area) -> None:
        """The anchor: a particle no operation of ``plan`` moves, nearest the area's centre."""
        moving = {op.object for op in plan.operations}
        cands = [o for o in belief.objects.values()
                 if o.id not in moving and o.kind == "particle" and not o.edge]
        if not cands:
            return
        cx, cy = area[0] / 2, area[1] / 2
        best = min(cands, key=lambda o: (math.dist(o.at, (cx, cy)), o.id))
        self.anchor = (best.id, best.at)

    def reference_target(self, t, near, obj_id, belief, refs, pushed, moving, options) -> str | None:
        return None if self.anchor is None else self.anchor[0]

    def measure_reference(self, obj_id, at, cov, t, refs, pushed, lost) -> bool | None:
        """The anchor found at ``at``: the offset. (Only the anchor's own reference scan
        measures; an object located before its push does not, even if it is the anchor.)"""
        if self.anchor is None or obj_id != self.anchor[0]:
            return None
        self.drift = np.asarray(at) - self.origin - np.asarray(self.anchor[1])
        return True

    def state_dict(self) -> dict:
        return {**super().state_dict(), "kind": "anchor",
                "anchor": None if self.anchor is None else [self.anchor[0], list(self.anchor[1])]}

    @classmethod
    def from_state(cls, state: dict, options: ExecOptions):
        out = super().from_state(state, options)
        a = state["anchor"]
        out.anchor = None if a is None else (a[0], tuple(a[1]))
        return out


def filter_params(options: ExecOptions) -> DriftFilterParams:
    """The drift filter's parameters for a run's options."""
    return DriftFilterParams(q=options.drift_q, q_offset=options.drift_q_offset, offset_std=1.0)


class Kalman:
    """Kalman and full: the drift filter, its references and the creep of the moves."""

    references_are_objects = True
    emits = True
    bootstraps = True

    def __init__(self, origin, epoch: float, options: ExecOptions):
        self.origin = np.asarray(origin, float)
        self.epoch = float(epoch)
        self.params = filter_params(options)
        self.filter = DriftFilter(self.params, epoch=self.epoch)
        self.move_log: list[tuple[float, np.ndarray]] = []   # replayed when restarted
        self.creep_anchor: np.ndarray | None = None   # where the last recorded move ended, nm

    def restart(self, velocity, var_velocity: float) -> None:
        """Start the filter afresh with a known velocity (the full scan's skew), the moves
        recorded so far replayed."""
        self.filter = DriftFilter(self.params, epoch=self.epoch,
                                  x0=np.array([0.0, 0.0, velocity[0], velocity[1]]),
                                  P0=np.diag([4.0, 4.0, var_velocity, var_velocity]))
        for t_move, step in self.move_log:
            self.filter.record_move(t_move, step)

    # -- the estimate ---------------------------------------------------------------------
    def offset(self, t: float) -> np.ndarray:
        return self.origin + np.asarray(self.filter.offset(t).offset, float)

    def velocity(self) -> np.ndarray:
        return np.asarray(self.filter.x[2:], float)

    def velocity_std(self) -> float:
        """Standard deviation of the velocity estimate's x component, nm/s."""
        return math.sqrt(self.filter.P[2, 2])

    def creep_offset(self, tau: float) -> np.ndarray:
        """The offset the recorded moves' creep is modelled to cause ``tau`` s after the epoch."""
        return self.filter.creep.offset(tau)

    def unskew(self, at: np.ndarray, tau: float) -> np.ndarray:
        """A full-scan position seen ``tau`` s after the epoch, its row's drift taken out
        with the present velocity and the creep modelled then."""
        return at - self.velocity() * tau - self.creep_offset(tau)

    def radius(self, t: float, seen, skew_tau: float | None, options: ExecOptions) -> float:
        """3σ error of a believed position: the offset's covariance, the sighting's, and
        for a full-scan position the skew with an uncertain velocity."""
        cov = np.asarray(self.filter.offset(t).cov, float)
        if seen is not None:
            cov = cov + seen.cov
            if skew_tau is not None:
                cov = cov + self.filter.P[2:, 2:] * skew_tau ** 2
        return 3.0 * math.sqrt(max(float(np.linalg.eigvalsh(cov)[-1]), 0.0))

    def observation_cov(self, t: float, cov) -> np.ndarray:
        """A measured pose's covariance in the layout frame: the drift estimate's added."""
        return np.asarray(cov, float) + np.asarray(self.filter.offset(t).cov, float)

    def clamp(self, t: float) -> float:
        return max(t, self.filter.time)

    def doc(self, t: float) -> dict:
        t = self.clamp(t)
        off = self.offset(t) - self.origin
        return {"t": t, "offset": [float(off[0]), float(off[1])],
                "cov": np.asarray(self.filter.offset(t).cov, float).tolist(),
                "velocity": [float(v) for v in self.filter.x[2:]]}

    # -- references -----------------------------------------------------------------------
    def after_plan(self, plan, belief, area) -> None:
        """The first plan is made: its references are chosen push by push."""

    def reference_target(self, t, near, obj_id, belief, refs, pushed, moving, options) -> str | None:
        """The untouched particle to measure before a push near ``near`` (None: not due,
        or none left): the nearest outside the reach of the push (a rod swings its ends
        half its length around; a reference the push may shove measures nothing)."""
        f = self.filter
        measured = f.measurements or f.resumed_measurements
        if measured and t - f.time < options.reference_every:
            return None
        candidates = [o for oid, o in belief.objects.items()
                      if refs.is_reference(oid, pushed, belief.lost) and oid not in belief.touched
                      and oid not in moving and o.kind == "particle" and not o.edge]
        if not candidates:
            return None
        target = belief[obj_id] if obj_id is not None else None
        reach = REFERENCE_GAP + (target.length if target is not None and target.elongated else 0.0)
        return min(candidates, key=lambda o: (math.dist(o.at, near) < reach, math.dist(o.at, near), o.id)).id

    def reference_position(self, refs: References, obj_id: str) -> tuple[np.ndarray, float]:
        """Layout position of a reference from the full scan alone, and ``tau``, when it
        was seen there after the epoch (later sightings carry old estimates: measuring
        against them lets the estimate's error walk)."""
        at, seen_t = refs.first_seen[obj_id]
        tau = seen_t - self.epoch
        return self.unskew(at, tau), tau

    def measure(self, obj_id, at, cov, t, refs, pushed, lost) -> bool | None:
        """Fold a reference's measured position (scanner frame) into the filter: None if
        it is no reference, else whether the gate accepted it (a rejected one moved on
        its own and is no reference from then on)."""
        if not refs.is_reference(obj_id, pushed, lost):
            return None
        ref, tau = self.reference_position(refs, obj_id)
        z = np.asarray(at) - self.origin - ref
        # the full scan's position, its skew corrected with an uncertain velocity
        R = cov + np.eye(2) * FULL_SCAN_VAR + self.filter.P[2:, 2:] * tau ** 2
        m = self.filter.measure(t, z, R, label=obj_id)
        if not m.accepted:
            refs.gated.add(obj_id)
        return bool(m.accepted)

    def measure_reference(self, obj_id, at, cov, t, refs, pushed, lost) -> bool | None:
        return self.measure(obj_id, at, cov, t, refs, pushed, lost)

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

    def pending_travel(self, dac, current, config) -> list:
        """The move a streamed path's own travel will be recorded as: ``[(t_end, step)]``,
        or ``[]`` if it is too short to creep."""
        from .trajectory import PUSH, TRAVEL

        prof = dac.profile
        travel = np.flatnonzero(prof.kind == TRAVEL)
        push = np.flatnonzero(prof.kind == PUSH)
        travel = travel[travel < push[0]] if push.size else travel
        if not travel.size:
            return []
        k = int(prof.ends[travel[-1]])
        if k < 1:
            return []
        end = dac.render(np.array([k])).nm[0, :2]
        anchor = (self.creep_anchor if self.creep_anchor is not None
                  else config.codes_to_nm(np.asarray(current))[:2])
        step = end - anchor
        if math.hypot(*step) < self.filter.params.creep.min_step:
            return []
        return [(dac.t0 + k / config.sample_rate, step)]

    def predicted(self, t0: float, pending=()):
        """Thermal drift and the creep of the recorded and ``pending`` moves from ``t0``."""
        creep = self.filter.creep
        thermal = self.offset(t0) - self.creep_offset(t0 - self.epoch)
        return CreepingOffset(thermal, self.velocity(), t0, creep, self.epoch, pending)

    # -- checkpoints ----------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"kind": "kalman", "origin": [float(v) for v in self.origin], "epoch": self.epoch,
                "filter": self.filter.state_dict(),
                "creep_anchor": None if self.creep_anchor is None else [float(v) for v in self.creep_anchor]}

    @classmethod
    def from_state(cls, state: dict, options: ExecOptions) -> Kalman:
        out = cls(state["origin"], state["epoch"], options)
        out.filter = DriftFilter.from_state(out.params, state["filter"])
        ca = state["creep_anchor"]
        out.creep_anchor = None if ca is None else np.asarray(ca, float)
        return out


_KINDS = {"none": NoDrift, "anchor": Anchor, "kalman": Kalman}


def estimator_for(strategy: Strategy, origin, epoch: float, options: ExecOptions) -> DriftEstimator:
    """The estimator a strategy uses."""
    if strategy.kalman:
        return Kalman(origin, epoch, options)
    if strategy.anchored:
        return Anchor(origin, epoch)
    return NoDrift(origin, epoch)


def estimator_from_state(state: dict, options: ExecOptions) -> DriftEstimator:
    """The estimator a checkpoint's ``state_dict()`` describes."""
    kind = state.get("kind")
    if kind not in _KINDS:
        raise ValueError(f"unknown drift estimator {kind!r}; one of {', '.join(_KINDS)}")
    return _KINDS[kind].from_state(state, options)
