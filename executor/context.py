"""The explicit state the steps of a run work on: the instrument's configuration, the run's
options, and its components (drift estimator, belief, full-scan references, ledger).

Steps (:mod:`~nanoasm.executor.scan_steps`, :mod:`~nanoasm.executor.motion_steps`,
:mod:`~nanoasm.executor.drift_steps`) are free generator functions over a
:class:`RunContext`, so each can be run against a fake instrument without a whole run.
Frames: the belief is in the layout frame; a layout point ``p`` lies at
``p + offset(t)`` in the scanner frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from nanoasm.bodies import Body
from nanoasm.world.environment import Environment

from .belief import Belief
from .estimators import DriftEstimator
from .landmarks import Landmarks
from .pivots import Pivots
from .ledger import RunLedger
from .reference_choice import LineTiming
from .references import References
from .scan_lines import ScanOptions
from .strategy import ExecOptions


@dataclass
class RunContext:
    """State shared by the steps of one run (see the module docstring).

    ``moving``: objects the current plan still moves (never drift references).
    ``scan_ref``: time of the running scan pattern's first line (its lines are
    compensated to that time), None between patterns; ``scan_comp``: the covariance of
    that compensation's error for the running pattern's worst line, ``scan_creep`` the
    creep (nominal amplitude) in each line's. ``landmarks``: the fixed features
    and relocalisation windows; ``timing``: what a scan line costs on this instrument;
    ``here``: the tip's last known XY (scanner frame); ``full_scan``: the first full scan
    in the layout frame and ``env_objects`` what it showed (neither kept in
    checkpoints: a run log holds them). ``corrected``: a relocalisation moved believed
    objects since the plan was last made (the plan is made again after the push);
    ``shoved``: neighbours a push shoved, located again since (:mod:`.shoves`; the run's
    loop brings placed ones back; neither kept in checkpoints).
    ``pivots``: every pushed rod's pose-and-pivot-offset filter. ``baselines``: the
    calibration's free-air maps A(i, j), B(i, j) the push monitor compensates with (not in
    checkpoints: the instrument's, given again on resuming). ``surveyed``: windows (layout
    frame) a repair round scanned for lost objects, not searched again (:mod:`.repair`;
    not in checkpoints: a resumed run may search them again)."""

    config: Any                         # the instrument's InstrumentConfig
    options: ExecOptions
    drift: DriftEstimator
    belief: Belief
    refs: References
    ledger: RunLedger = field(default_factory=RunLedger)
    scan_opts: ScanOptions | None = None
    moving: set[str] = field(default_factory=set)
    scan_ref: float | None = None
    scan_comp: np.ndarray = field(default_factory=lambda: np.zeros((2, 2)))
    scan_creep: list = field(default_factory=list)
    landmarks: Landmarks = field(default_factory=Landmarks)
    timing: LineTiming = field(default_factory=LineTiming)
    here: np.ndarray | None = None
    full_scan: Any = None
    env_objects: tuple = ()
    corrected: bool = False
    shoved: set[str] = field(default_factory=set)
    pivots: Pivots = field(default_factory=Pivots)
    baselines: Any = None               # the detector's BaselineMaps (eq. 3.28-3.29); None: free air
    surveyed: list = field(default_factory=list)
    #: the last push's after-scan: [object, its time, the drift estimate's revision then,
    #: pushes so far], from which the next push of that object may start (:mod:`.pushing`)
    last_after: list | None = None
    #: pushes deferred for a replan, by object (:func:`~.pushing.deferred`; not in checkpoints)
    deferrals: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.scan_opts is None:
            self.scan_opts = ScanOptions(spacing=self.options.scan_spacing)

    def offset(self, t: float) -> np.ndarray:
        """Scanner position of the layout's origin at ``t`` (the drift estimate's)."""
        return self.drift.offset(t)

    def position(self, obj_id: str) -> np.ndarray:
        """Believed layout position; an object seen only in the first full scan is moved by
        the drift during that scan (row by row), as far as the estimate knows it."""
        at = np.asarray(self.belief[obj_id].at, float)
        if obj_id in self.refs.raw:
            at = self.drift.unskew(at, self.belief.seen[obj_id].t - self.drift.epoch)
        return at

    def r_max(self, t: float, obj_id: str | None = None, full_scan=None) -> float:
        """Largest expected error of a believed position at ``t``, nm, scaled by the
        options' ``line_factor`` (at least ``r_max_floor``). ``full_scan``: the
        covariance of where the full scan's row of ``obj_id`` now lies, when known."""
        o = self.options
        seen = self.belief.seen.get(obj_id) if obj_id is not None else None
        skew = seen.t - self.drift.epoch if seen is not None and obj_id in self.refs.raw else None
        return o.line_factor * max(self.drift.radius(t, seen, skew, o, full_scan), o.r_max_floor)

    def to_layout(self, scanner: Body, t: float) -> Body:
        """A measured pose (scanner frame) in the layout frame, by the present estimate."""
        at = np.asarray(scanner.at) - self.offset(t)
        return replace(scanner, at=(float(at[0]), float(at[1])))

    def add_new(self, kind: str, at, height: float, like, t: float, cov) -> str:
        """An object seen where none is believed (:meth:`Belief.add_new`); its id. One not a
        particle is given up, an obstacle never assigned: its shape is not known (seen while
        looking for a rod, its length and angle are the rod's, not what was seen: device
        seed 2 on 2e65012 assigned such a copy the rod's slot, which got "no path")."""
        new = self.belief.add_new(kind, at, height, like, t, cov)
        if kind != "particle":
            self.ledger.given_up.add(new)
        return new

    def observe(self, obj_id: str, at, t: float, cov, *, angle=None) -> None:
        """Record a measured pose (layout frame); its uncertainty includes the drift
        estimate's at ``t``, through which it was put into the layout frame."""
        self.belief.observe(obj_id, at, t, self.drift.observation_cov(t, cov), angle=angle)
        self.refs.raw.discard(obj_id)

    def log_drift(self, t: float) -> None:
        off = self.offset(t)
        self.ledger.drift.append((t, float(off[0]), float(off[1])))

    def positions(self, ids) -> np.ndarray:
        """:meth:`position` of each of ``ids``, ``(n, 2)``: those seen only in the first full
        scan moved by their rows' drift in one product, each to the bit as one by one."""
        belief, raw = self.belief, self.refs.raw
        out = np.array([belief[i].at for i in ids], float).reshape(-1, 2)
        skewed = [k for k, i in enumerate(ids) if i in raw]
        if skewed:
            tau = np.array([belief.seen[ids[k]].t - self.drift.epoch for k in skewed])
            out[skewed] = self.drift.unskew(out[skewed], tau)
        return out

    def environment(self) -> Environment:
        """The belief as the planner's environment: objects seen only in the first full
        scan moved by their row's drift, lost ones left out (where they were believed to
        be is where the scans did not find them). Objects given up on
        (:attr:`ExecOptions.max_failures`) are never assigned: they stay, obstacles."""
        belief, raw, given_up = self.belief, self.refs.raw, self.ledger.given_up
        objs = [o for o in belief.objects.values() if o.id not in belief.lost]
        at = self.positions([o.id for o in objs]).tolist()
        objs = [o.changed(at=(x, y)) if o.id in raw else o for o, (x, y) in zip(objs, at)]
        objs = [o.changed(confidence=0.0) if o.id in given_up else o for o in objs]
        return Environment(self.belief.area, tuple(objs), self.belief.obstacles, "belief")
