"""Drift estimators: where the layout's origin lies in the scanner frame, and how well that
is known, for each way a run handles drift.

A strategy picks one (:func:`estimator_for`):

* :class:`NoDrift` (open-loop, local-scan): the origin stays where the run started;
  a believed position is off by at most ``r_max`` plus ``max_drift_rate`` times the
  time since the object was last seen.
* :class:`Anchor` (anchor): one fixed particle, scanned before every push, gives the
  offset directly.
* :class:`~nanoasm.executor.kalman_drift.Kalman` (kalman, full): the drift filter of
  :mod:`nanoasm.drift`, fed by objects never pushed (measured against their full-scan
  position) and by fixed features, with the creep of every recorded scanner move.

Each is plain state with ``state_dict()``/``from_state()``; scanning is the steps' job
(:mod:`nanoasm.executor.drift_steps`), which ask an estimator what to measure and tell it
what they found. Positions are nm, times instrument seconds.
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np

from .dac_frames import LinearDrift
from .kalman_drift import Kalman
from .reference_choice import Candidate
from .references import References
from .strategy import ExecOptions, Strategy


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
    #: whether it measures fixed features and relocalises (:mod:`.landmarks`)
    uses_landmarks: bool

    def offset(self, t: float) -> np.ndarray: ...
    def revision(self) -> object: ...
    def compensation(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]: ...
    def velocity(self) -> np.ndarray: ...
    def unskew(self, at: np.ndarray, tau) -> np.ndarray: ...     # tau a float, or (n,) with at (n, 2)
    def radius(self, t: float, seen, skew_tau: float | None, options: ExecOptions, full_scan=None) -> float: ...
    def observation_cov(self, t: float, cov) -> np.ndarray: ...
    def clamp(self, t: float) -> float: ...
    def doc(self, t: float) -> dict: ...
    def after_plan(self, plan, belief, area) -> None: ...
    def reference_target(self, ctx, t: float, near, obj_id, *, force: bool = False) -> Candidate | None: ...
    def measure(self, obj_id: str, at, cov, t: float, refs: References, pushed, lost,
                creep_sens=None) -> bool | None: ...
    def measure_reference(self, obj_id: str, at, cov, t: float, refs: References, pushed,
                          lost, creep_sens=None) -> bool | None: ...
    def measure_feature(self, feature_id: str, z, H, R, t: float, taus=None, creep_sens=None) -> bool: ...
    def needs_relocalisation(self, t: float, options: ExecOptions) -> tuple[str, str] | None: ...
    def relocalised(self, t: float, offset, cov, refs: References) -> list[str]: ...
    def relocalise_failed(self, t: float) -> None: ...
    def resumed(self, pause: float) -> None: ...
    def reject(self, label: str, t: float) -> None: ...
    def moved_to(self, xy, t: float, start=None) -> None: ...
    def moved_along(self, xy, t, start=None, rests=()) -> None: ...
    def pending_moves(self, dac, current, config) -> list: ...
    def predicted(self, t0: float, pending=()): ...
    def state_dict(self) -> dict: ...


class NoDrift:
    """Open-loop and local-scan: no drift is estimated; the origin stays put."""

    references_are_objects = False
    emits = False
    bootstraps = False
    uses_landmarks = False
    velocity_known = False

    def __init__(self, origin, epoch: float):
        self.origin = np.asarray(origin, float)
        self.epoch = float(epoch)
        self.drift = np.zeros(2)          # the estimated drift since the epoch, nm

    def offset(self, t: float) -> np.ndarray:
        """Scanner position of the layout's origin at ``t``."""
        return self.origin + self.drift

    def velocity(self) -> np.ndarray:
        return np.zeros(2)

    def revision(self) -> object:
        """A token equal to an earlier one while the estimate was not revised since."""
        return [float(v) for v in self.drift]

    def compensation(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
        """The creep (nm, nominal amplitude) within ``offset(t1) - offset(t0)``, by which
        a scan pattern's line at ``t1`` is shifted to see the sample as it lay at ``t0``,
        and the covariance (nm²) of that shift's error: neither is modelled here (the
        drift is not estimated, so its bound covers it)."""
        return np.zeros(2), np.zeros((2, 2))

    def unskew(self, at: np.ndarray, tau) -> np.ndarray:
        """Full-scan positions with their rows' drift taken out (none known here)."""
        return at

    def radius(self, t: float, seen, skew_tau: float | None, options: ExecOptions, full_scan=None) -> float:
        """3σ error of a believed position last seen at ``seen`` (None: never): r_max plus
        the drift that can have built up at ``max_drift_rate`` since (no full scan's
        row drift here: ``full_scan`` is not used)."""
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

    def reference_target(self, ctx, t, near, obj_id, *, force: bool = False) -> Candidate | None:
        """The reference to scan for drift before a push of ``obj_id`` near ``near`` (None here)."""
        return None

    def measure(self, obj_id, at, cov, t, refs, pushed, lost, creep_sens=None) -> bool | None:
        """Fold any located object's measured position (scanner frame) in: None (not
        used), True, or False (gated out)."""
        return None

    def measure_reference(self, obj_id, at, cov, t, refs, pushed, lost, creep_sens=None) -> bool | None:
        """Fold the measured position of the reference :meth:`reference_target` chose."""
        return None

    def measure_feature(self, feature_id, z, H, R, t, taus=None, creep_sens=None) -> bool:
        """Fold a fixed feature's measurement (never chosen here)."""
        raise TypeError("this estimator takes no fixed features (it never chooses one)")

    def needs_relocalisation(self, t: float, options: ExecOptions) -> tuple[str, str] | None:
        """Nothing is estimated here, so nothing is relocalised."""
        return None

    def relocalised(self, t, offset, cov, refs) -> list[str]:
        raise TypeError("this estimator has no estimate to relocalise")

    def relocalise_failed(self, t: float) -> None:
        raise TypeError("this estimator has no estimate to relocalise")

    def resumed(self, pause: float) -> None:
        """The run resumes after standing still ``pause`` s (nothing to widen here)."""

    def reject(self, label: str, t: float) -> None:
        """A reference was not found (none is kept here)."""

    def moved_to(self, xy, t: float, start=None) -> None:
        """The scanner reached ``xy`` at ``t`` (creep is not modelled here)."""

    def moved_along(self, xy, t, start=None, rests=()) -> None:
        """The scanner went through ``xy`` at times ``t`` (creep is not modelled here)."""

    def pending_moves(self, dac, current, config) -> list:
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

    def reference_target(self, ctx, t, near, obj_id, *, force: bool = False) -> Candidate | None:
        if self.anchor is None:
            return None
        return Candidate("object", self.anchor[0], np.eye(2), np.eye(2), 0.0, 1.0)

    def measure_reference(self, obj_id, at, cov, t, refs, pushed, lost, creep_sens=None) -> bool | None:
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
