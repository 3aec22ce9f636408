"""The assembly procedure: full scan -> identify -> plan -> for every push: reference scans,
a local scan before, the push streamed with drift folded in and its signals watched, a
local scan after, corrections or replanning -> checkpoint.

It is a generator of :class:`~nanoasm.executor.engine.Msg` run by the
:class:`~nanoasm.executor.engine.RunEngine`; it never touches an instrument (nor a
simulated truth) itself. Frames: positions in the plan and the belief are in the layout
frame (the frame of the first full scan); a layout point ``p`` is at ``p + offset(t)`` in
the scanner frame, with ``offset`` the drift estimate of the strategy.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Generator
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import shapely

from nanoasm.bodies import Body
from nanoasm.cad.layout import Layout
from nanoasm.drift import DriftFilter, DriftFilterParams
from nanoasm.drift.creep import CreepingOffset
from nanoasm.planner import Operation, Plan, PlanOptions, Replanner
from nanoasm.planner.assign import in_slot
from nanoasm.planner.plan import Assignment, Unfilled
from nanoasm.world.cantilever import SEED_LEVER, Cantilever
from nanoasm.world.environment import Environment
from nanoasm.world.identify import identify

from .belief import Belief
from .dac import plan_dac
from .dac_frames import LinearDrift
from .trajectory import PUSH, TRAVEL, operation
from .engine import Msg
from .local_scan import particle_after, particle_before, rod_after, rod_before
from .lost_search import find_lost_particle
from .monitor import PushMonitor, Verdict
from .reaim import particle_push, rod_push
from .report import Counts
from .scan_lines import ScanOptions
from .strategy import ExecOptions

Procedure = Generator[Msg, Any, "RunSummary"]
ACTIVITIES = ("full_scan", "local_scan", "push", "travel")
#: A scan line starting farther than this (nm) from the tip is preceded by a travel.
APPROACH = 300.0
#: A drift reference is chosen at least this far (nm, plus a rod's length) from the push.
REFERENCE_GAP = 300.0
#: Variance (nm² per axis) of an object's position in the first full scan, its row's
#: drift aside (identification measured 0.28 nm on centres; 2 nm covers pixel effects).
FULL_SCAN_VAR = 4.0


@dataclass
class RunSummary:
    """What a run did, for the report (the truth is the caller's, in a dry-run)."""

    env: Environment                      # identified at the start
    plan: Plan                            # first plan
    belief: Belief
    assignment: tuple[Assignment, ...] = ()
    unfilled: tuple[Unfilled, ...] = ()
    pushed: list[str] = field(default_factory=list)
    counts: Counts = Counts()
    times: dict[str, float] = field(default_factory=dict)
    wall: dict[str, float] = field(default_factory=dict)
    drift: list[tuple[float, float, float]] = field(default_factory=list)   # (t, dx, dy) estimates
    failures: list[tuple[str, str]] = field(default_factory=list)          # (object, cause)
    epoch: float = 0.0            # start of the run: the layout frame's time
    origin: tuple[float, float] = (0.0, 0.0)   # layout origin in the scanner frame at the epoch


class Assembly:
    """State and steps of one unattended assembly run (see the module docstring)."""

    def __init__(self, layout: Layout, options: ExecOptions | None = None,
                 plan_options: PlanOptions | None = None, *, lever: Cantilever = SEED_LEVER):
        self.layout = layout
        self.options = options or ExecOptions()
        self.plan_options = plan_options or PlanOptions()
        self.strategy = self.options.strategy
        self.lever = lever
        self.replanner = Replanner(layout, self.plan_options)
        self.counts = {"pushes": 0, "local_scans": 0, "replans": 0, "failed_pushes": 0}
        self.times = dict.fromkeys(ACTIVITIES, 0.0)
        self.wall = {"identify": 0.0, "plan": 0.0, "execute": 0.0}
        self.pushed: list[str] = []
        self.first_seen: dict[str, tuple[np.ndarray, float]] = {}   # full-scan position, time
        self.no_reference: set[str] = set()     # gated out once: moved on its own
        self.troubles: dict[str, int] = {}      # pushes failed or gone astray, per object
        self.given_up: set[str] = set()         # left where they are after max_failures
        self.failures: list[tuple[str, str]] = []
        self.drift_log: list[tuple[float, float, float]] = []
        self.filter: DriftFilter | None = None
        self.anchor: tuple[str, tuple[float, float]] | None = None
        self.env: Environment | None = None        # identified by the first full scan
        self.first_plan: Plan | None = None
        self.anchor_offset = np.zeros(2)
        self.config = None
        self.scan_opts = ScanOptions()
        self.raw: set[str] = set()
        self.moving: set[str] = set()            # objects the current plan still moves
        self._plan_start: dict[int, tuple] = {}  # pose each operation expects to start from
        self.preload_factor: dict[str, float] = {}
        self.move_log: list[tuple[float, np.ndarray]] = []
        self._creep_anchor: np.ndarray | None = None   # where the last recorded move ended, nm
        self._scan_ref: float | None = None   # time of the running pattern's first line
        self.epoch = 0.0
        self.origin = np.zeros(2)

    # -- the drift estimate ---------------------------------------------------------
    def offset(self, t: float) -> np.ndarray:
        """Scanner position of the layout's origin at ``t``: where the run scanned first
        plus the drift estimate of the strategy."""
        if self.filter is not None:
            return self.origin + np.asarray(self.filter.offset(t).offset, float)
        return self.origin + self.anchor_offset

    def offset_velocity(self) -> np.ndarray:
        return np.asarray(self.filter.x[2:], float) if self.filter is not None else np.zeros(2)

    def position(self, obj_id: str) -> np.ndarray:
        """Believed layout position; an object seen only in the first full scan is moved by
        the drift during that scan (row by row), as far as the drift velocity is known."""
        at = np.asarray(self.belief[obj_id].at, float)
        if obj_id in self.raw and self.filter is not None:
            tau = self.belief.seen[obj_id].t - self.epoch
            at = at - self.offset_velocity() * tau - self.filter.creep.offset(tau)
        return at

    def r_max(self, t: float, obj_id: str | None = None) -> float:
        """Largest expected error of a believed position at ``t``, nm: from the drift
        filter's covariance, or (no filter) ``r_max`` plus the drift that can have built up
        at ``max_drift_rate`` since the object was last seen."""
        o = self.options
        if self.filter is not None:
            cov = np.asarray(self.filter.offset(t).cov, float)
            seen = self.belief.seen.get(obj_id) if obj_id is not None else None
            if seen is not None:
                cov = cov + seen.cov
                if obj_id in self.raw:     # skew of the full scan, with an uncertain velocity
                    cov = cov + self.filter.P[2:, 2:] * (seen.t - self.epoch) ** 2
            r = 3.0 * math.sqrt(max(float(np.linalg.eigvalsh(cov)[-1]), 0.0))
        else:
            since = t - self.belief.seen[obj_id].t if obj_id in self.belief.seen else 0.0
            r = o.r_max + o.max_drift_rate * max(since, 0.0)
        return o.line_factor * max(r, o.r_max_floor)

    # -- building blocks (generators) -----------------------------------------------
    def _scan(self, pattern):
        """Run a local-scan pattern through scan_line messages; returns its result."""
        t0 = yield Msg("clock")
        travel0 = self.times["travel"]
        self.counts["local_scans"] += 1
        self._scan_ref = None
        try:
            line = next(pattern)
            while True:
                profile = yield from self._scan_line(np.asarray(line.a, float), np.asarray(line.b, float),
                                                     int(line.n))
                line = pattern.send(profile)
        except StopIteration as stop:
            result = stop.value
        t1 = yield Msg("clock")
        # the travels to the lines are counted as travel, not twice
        self.times["local_scan"] += t1 - t0 - (self.times["travel"] - travel0)
        return result

    def _scan_line(self, a: np.ndarray, b: np.ndarray, n: int):
        """A scan line, cut to the scanner's range: samples beyond it read as bare
        substrate (the median of the rest), so a pattern near the range's edge still works.

        The lines of one pattern are drift-compensated: each is shifted by the offset
        predicted since the pattern's first line (``_scan_ref``), so the pattern sees the
        sample as it lay then, however fast creep moves it after a travel, and its result
        is converted with the offset of that time."""
        yield from self._approach(a)
        t_line = yield Msg("clock")
        if self._scan_ref is None:
            self._scan_ref = t_line
        shift = self.offset(t_line) - self.offset(self._scan_ref)
        a, b = a + shift, b + shift
        lo, hi = self.config.lower[:2], self.config.upper[:2]
        s = np.linspace(0.0, 1.0, n)
        pts = a[None, :] + s[:, None] * (b - a)[None, :]
        inside = np.all((pts >= lo) & (pts <= hi), axis=1)
        if inside.all():
            t0 = yield Msg("clock")
            profile = np.asarray((yield Msg("scan_line", (tuple(a), tuple(b), n))), float)
            t = yield Msg("clock")
            self._moved_to(a, t0)
            self._moved_to(b, t)
            yield Msg("emit", ("scan_line", self._line_doc(a, b, profile, t)))
            return profile
        idx = np.flatnonzero(inside)
        if idx.size < 2:
            return np.zeros(n)
        i0, i1 = int(idx[0]), int(idx[-1])
        t0 = yield Msg("clock")
        part = np.asarray((yield Msg("scan_line", (tuple(pts[i0]), tuple(pts[i1]), i1 - i0 + 1))), float)
        t = yield Msg("clock")
        self._moved_to(pts[i0], t0)
        self._moved_to(pts[i1], t)
        out = np.full(n, float(np.median(part)))
        out[i0:i1 + 1] = part
        yield Msg("emit", ("scan_line", self._line_doc(a, b, out, t)))
        return out

    def _locate(self, obj_id: str):
        """Local scan of an object where it is believed to be; widening search if missed.

        Returns (measured pose in the *scanner* frame, covariance, time, scan result) or
        None (lost). Convert with :meth:`_layout` after any drift update.
        """
        o = self.belief[obj_id]
        t = yield Msg("clock")
        off = self.offset(t)
        r_max = self.r_max(t, obj_id)
        at = self.position(obj_id) + off
        if o.kind == "rod":
            pattern = rod_before(at, o.angle, o.length, o.diameter, r_max, measure_angle=True,
                                 options=self.scan_opts)
        else:
            pattern = particle_before(at, o.diameter, r_max, options=self.scan_opts)
        res = yield from self._scan(pattern)
        if not res.found:
            yield Msg("event", (f"{obj_id} not found within {r_max:.0f} nm; widening search",), {"level": "warn"})
            res = yield from self._scan(find_lost_particle(at, o.diameter, self.options.lost_radius,
                                                           options=replace(self.scan_opts, max_lines=400)))
            if res.found and o.kind == "rod":
                res = yield from self._scan(rod_before(res.centre, o.angle, o.length, o.diameter,
                                                       2 * o.diameter, measure_angle=True, options=self.scan_opts))
            if not res.found or self._someone_else(obj_id, np.asarray(res.centre, float) - off):
                return None
        t = self._scan_ref if self._scan_ref is not None else (yield Msg("clock"))
        centre = np.asarray(res.centre, float)
        angle = res.angle if o.kind == "rod" and res.angle is not None else o.angle
        body = Body(o.id, o.kind, (float(centre[0]), float(centre[1])), o.diameter,
                    angle if o.elongated else None, o.length if o.elongated else None)
        cov = res.cov if res.cov is not None else np.eye(2) * 4.0
        return body, np.asarray(cov, float), t, res

    def _layout(self, scanner: Body, t: float) -> Body:
        """A measured pose (scanner frame) in the layout frame, by the present estimate."""
        at = np.asarray(scanner.at) - self.offset(t)
        return replace(scanner, at=(float(at[0]), float(at[1])))

    def _someone_else(self, obj_id: str, at: np.ndarray, expected: np.ndarray | None = None) -> bool:
        """Whether a scan hit another known object rather than ``obj_id`` (expected at
        ``expected``, by default where it is believed to be)."""
        mine = math.dist(at, self.position(obj_id) if expected is None else expected)
        d = self.belief[obj_id].diameter
        return any(math.dist(at, self.position(oid)) < min(mine, d)
                   for oid in self.belief.objects if oid != obj_id and oid not in self.belief.lost)

    def _is_reference(self, obj_id: str) -> bool:
        """Whether an object may measure drift: never pushed, never gated out."""
        return (obj_id in self.first_seen and obj_id not in self.pushed
                and obj_id not in self.no_reference and obj_id not in self.belief.lost)

    def _environment(self) -> Environment:
        """The belief as the planner's environment: objects seen only in the first full
        scan moved by their row's drift (:meth:`position`), lost ones left out (where they
        were believed to be is where the scans did not find them). Objects given up on
        (:attr:`ExecOptions.max_failures`) are never assigned: they stay, obstacles."""
        objs = []
        for o in self.belief.objects.values():
            if o.id in self.belief.lost:
                continue
            if o.id in self.raw and self.filter is not None:
                o = replace(o, at=tuple(float(v) for v in self.position(o.id)))
            if o.id in self.given_up:
                o = replace(o, confidence=0.0)
            objs.append(o)
        return Environment(self.belief.area, tuple(objs), self.belief.obstacles, "belief")

    def _reference_position(self, obj_id: str) -> tuple[np.ndarray, float]:
        """Layout position of a reference object from the full scan alone, and the time
        it was seen there: the row's drift taken out with the present velocity estimate.

        Later sightings are not used: each was put into the layout frame with the drift
        estimate of its time, so measuring against it would measure drift relative to
        an old estimate and let the estimate's error walk (a rod pushed sixty times in a
        row moved the estimate 30 nm that way)."""
        at, seen_t = self.first_seen[obj_id]
        tau = seen_t - self.epoch
        if self.filter is not None:
            at = at - self.offset_velocity() * tau - self.filter.creep.offset(tau)
        return at, tau

    def _drift_measurement(self, obj_id: str, measured: Body, cov: np.ndarray, t: float) -> bool:
        """Fold a reference object's measured position (scanner frame) into the drift
        filter; False if gated out (the object moved on its own: it is no reference
        from then on)."""
        if self.filter is None or not self._is_reference(obj_id):
            return True
        ref, tau = self._reference_position(obj_id)
        z = np.asarray(measured.at) - self.origin - ref
        # the full scan's position, its skew corrected with an uncertain velocity
        R = cov + np.eye(2) * FULL_SCAN_VAR + self.filter.P[2:, 2:] * tau ** 2
        m = self.filter.measure(t, z, R, label=obj_id)
        self._log_drift(t)
        if not m.accepted:
            self.no_reference.add(obj_id)
        return bool(m.accepted)

    def _observe(self, obj_id: str, at, t: float, cov, *, angle=None) -> None:
        """Record a measured pose (layout frame); its uncertainty includes the drift
        estimate's at ``t``, through which it was put into the layout frame."""
        if self.filter is not None:
            cov = np.asarray(cov, float) + np.asarray(self.filter.offset(t).cov, float)
        self.belief.observe(obj_id, at, t, cov, angle=angle)
        self.raw.discard(obj_id)

    def _log_drift(self, t: float) -> None:
        off = self.offset(t)
        self.drift_log.append((t, float(off[0]), float(off[1])))

    # -- documents for the run log (emitted; subscribers such as RunLog keep them) -----
    def _drift_doc(self, t: float) -> dict:
        """The drift estimate at ``t``: offset since the start (nm), its covariance (nm²;
        None without a filter) and the drift velocity (nm/s)."""
        if self.filter is not None:
            t = max(t, self.filter.time)
        off = self.offset(t) - self.origin
        doc = {"t": t, "offset": [float(off[0]), float(off[1])], "cov": None, "velocity": None}
        if self.filter is not None:
            doc["cov"] = np.asarray(self.filter.offset(t).cov, float).tolist()
            doc["velocity"] = [float(v) for v in self.filter.x[2:]]
        return doc

    def _emit_drift(self, t: float):
        """Emit the drift estimate after a filter or anchor update."""
        if self.filter is not None or self.strategy.anchored:
            yield Msg("emit", ("drift", self._drift_doc(t)))

    def _line_doc(self, a, b, heights, t: float) -> dict:
        """A local-scan line: end points (scanner frame), heights, and the scanner position
        of the layout origin as estimated then (layout = scanner - offset)."""
        off = self.offset(t if self.filter is None else max(t, self.filter.time))
        return {"t": t, "a": [float(a[0]), float(a[1])], "b": [float(b[0]), float(b[1])],
                "heights": np.asarray(heights, float).tolist(), "offset": [float(off[0]), float(off[1])]}

    def _dac_doc(self, codes, kind, block, every: int = 50) -> dict:
        """A streamed DAC chunk, every ``every``-th sample: scanner nm, kind, signals."""
        nm = self.config.codes_to_nm(np.asarray(codes)[::every])
        return {"t": block.t[::every].tolist(), "x": nm[:, 0].tolist(), "y": nm[:, 1].tolist(),
                "z": nm[:, 2].tolist(), "kind": np.asarray(kind)[::every].tolist(),
                "s_n": block.s_n[::every].tolist(), "s_l": block.s_l[::every].tolist(),
                "n": int(len(codes)), "every": every}

    def _reference(self, near: tuple[float, float], obj_id: str | None = None):
        """Measure drift on an untouched object (kalman/full) or the anchor (anchor)."""
        t = yield Msg("clock")
        if self.strategy.anchored and self.anchor is not None:
            aid, home = self.anchor
            found = yield from self._locate(aid)
            if found is not None:
                body, cov, t, _ = found
                self.anchor_offset = np.asarray(body.at) - self.origin - np.asarray(home)
                self._log_drift(t)
                yield from self._emit_drift(t)
            return
        if self.filter is None:
            return
        measured = self.filter.measurements or self.filter.resumed_measurements
        if measured and t - self.filter.time < self.options.reference_every:
            return
        candidates = [o for oid, o in self.belief.objects.items()
                      if self._is_reference(oid) and oid not in self.belief.touched
                      and oid not in self.moving and o.kind == "particle" and not o.edge]
        if not candidates:
            return
        # the nearest one outside the reach of the push to come (a rod swings its ends
        # half its length around): a reference the push may shove measures nothing
        pushed = self.belief[obj_id] if obj_id is not None else None
        reach = REFERENCE_GAP + (pushed.length if pushed is not None and pushed.elongated else 0.0)
        ref = min(candidates, key=lambda o: (math.dist(o.at, near) < reach, math.dist(o.at, near), o.id))
        found = yield from self._locate(ref.id)
        if found is None:
            self.belief.lose(ref.id)
            return
        body, cov, t, _ = found
        if not self._drift_measurement(ref.id, body, cov, t):
            yield Msg("event", (f"{ref.id} moved on its own (gated out of the drift estimate)",),
                      {"level": "warn"})
        yield from self._emit_drift(t)
        self._observe(ref.id, self._layout(body, t).at, t, cov)

    # -- one push -------------------------------------------------------------------
    def _stream(self, op: Operation):
        """Travel to the push, lower, push, lift; watching the signals. Returns the verdict."""
        # an object the tip slipped over before is pushed harder (seed eq. 4.7: a larger
        # normal force keeps the tip down), up to half the Z range
        cfg = self.config
        factor = self.preload_factor.get(op.object, 1.0)
        if factor != 1.0:
            cfg = replace(cfg, preload=min(cfg.preload * factor, 0.45 * cfg.z_range))
        current = yield Msg("position")
        t0 = yield Msg("clock")
        moves = operation(op.tip_path, push_speed=self.options.push_speed)
        dac = plan_dac(moves, cfg, current, t0=t0, drift=self._predicted_drift(t0), lever=self.lever)
        pending = self._pending_travel(dac, current)
        if pending:     # the travel to the push creeps while the push runs: follow it
            dac = plan_dac(moves, cfg, current, t0=t0, drift=self._predicted_drift(t0, pending),
                           lever=self.lever)
        monitor = PushMonitor(cfg.preload, lever=self.lever, force_limit=self.options.force_limit)
        verdict = None
        n_push = n_other = 0
        travel_end = push_end = None
        for chunk in dac.chunks(self.options.chunk):
            block = yield Msg("write", (chunk.codes,))
            yield Msg("emit", ("dac", self._dac_doc(chunk.codes, chunk.kind, block)))
            # creep follows the travel and the push as two moves, each ended where XY stops
            for kind, mark in ((TRAVEL, "travel"), (PUSH, "push")):
                idx = np.flatnonzero(chunk.kind == kind)
                if idx.size:
                    end = (chunk.codes[idx[-1]], float(block.t[idx[-1]]))
                    if mark == "travel":
                        travel_end = end
                    else:
                        push_end = end
            lifted = chunk.kind == 0                                   # travel: free air
            if lifted.any() and not monitor.in_contact:
                monitor.set_baseline(block.s_n[lifted], block.s_l[lifted])
            pushing = chunk.kind == 2
            n_push += int(pushing.sum())
            n_other += int((~pushing).sum())
            if pushing.any():
                v = monitor.check(block.s_n[pushing], block.s_l[pushing])
                if v.failed:
                    verdict = v
                    break
        for end in (travel_end, push_end):
            if end is not None:
                self._moved(current, *end)
        if verdict is None:
            verdict = monitor.finish()
        if verdict.failed:
            yield from self._lift()
        rate = cfg.sample_rate
        self.times["push"] += n_push / rate
        self.times["travel"] += n_other / rate
        return verdict

    def _predicted_drift(self, t0: float, pending=()):
        """The scanner offset of the layout origin as a function of time from ``t0``: the
        filter's thermal drift and the creep of the recorded moves and of ``pending``
        ones ``(t_end, step)`` (instrument s, nm)."""
        if self.filter is None:
            return LinearDrift(tuple(self.offset(t0)), (0.0, 0.0), t0)
        creep = self.filter.creep
        thermal = self.offset(t0) - creep.offset(t0 - self.epoch)
        return CreepingOffset(thermal, self.offset_velocity(), t0, creep, self.epoch, pending)

    def _pending_travel(self, dac, current) -> list:
        """The move the push's own travel will be recorded as (see :meth:`_moved_to`):
        ``[(t_end, step)]``, or ``[]`` if it is too short to creep."""
        if self.filter is None:
            return []
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
        anchor = (self._creep_anchor if self._creep_anchor is not None
                  else self.config.codes_to_nm(np.asarray(current))[:2])
        step = end - anchor
        if math.hypot(*step) < self.filter.params.creep.min_step:
            return []
        return [(dac.t0 + k / self.config.sample_rate, step)]

    def _travel_to(self, xy):
        """Lifted travel to ``xy`` (scanner frame nm) within the slew limit."""
        from nanoasm.world.instrument import ramp

        cfg = self.config
        here = yield Msg("position")
        there = cfg.nm_to_codes(np.array([xy[0], xy[1], cfg.lift]))
        path = ramp(here, there, cfg)
        if len(path):
            block = yield Msg("write", (path,))
            self.times["travel"] += len(block) / cfg.sample_rate
            self._moved(here, there, float(block.t[-1]))

    def _approach(self, xy):
        """Travel (lifted, recorded for creep) to a scan line that starts far from the tip,
        so the scan itself is a small move."""
        here = yield Msg("position")
        there = self.config.codes_to_nm(np.asarray(here))[:2]
        if math.dist(there, xy) > APPROACH:
            lo, hi = self.config.lower[:2], self.config.upper[:2]
            yield from self._travel_to(np.clip(np.asarray(xy, float), lo, hi))

    def _moved(self, start_codes, end_codes, t: float) -> None:
        """Tell the drift filter about a scanner move from ``start_codes`` finished at ``t``."""
        cfg = self.config
        self._moved_to(cfg.codes_to_nm(np.asarray(end_codes))[:2], t,
                       start=cfg.codes_to_nm(np.asarray(start_codes))[:2])

    def _moved_to(self, xy, t: float, start=None) -> None:
        """The scanner reached ``xy`` (nm) at ``t``: creep follows the step from where the
        last recorded move ended. A step shorter than the creep model's ``min_step`` is
        not recorded and does not restart the chain, so its displacement is carried into
        the next move: every displacement creeps, only its time is coarsened."""
        if self.filter is None:
            return
        xy = np.asarray(xy, float)
        if self._creep_anchor is None:
            self._creep_anchor = np.asarray(xy if start is None else start, float)
        step = xy - self._creep_anchor
        if math.hypot(*step) >= self.filter.params.creep.min_step:
            self._record(step, t)
            self._creep_anchor = xy

    def _record(self, step, t: float) -> None:
        if self.filter is None:
            return
        t = max(t, self.filter.time)
        step = np.asarray(step, float)
        self.move_log.append((t, step))
        self.filter.record_move(t, step)

    def _bootstrap(self):
        """The drift velocity from the full scan's own distortion.

        A full scan takes minutes: an object on row ``i`` was imaged at ``τ_i`` and the
        identified position carries the drift ``o(τ_i)``. Scanning a few objects again
        from bottom to top rows gives ``z_i = o(t_i) − o(τ_i) = v (t_i − τ_i)``: the velocity
        by least squares, which starts the drift filter (and corrects every other object
        of the first scan for its row's drift).
        """
        cands = sorted((o for o in self.belief.objects.values() if o.kind == "particle" and not o.edge),
                       key=lambda o: self.belief.seen[o.id].t)
        if len(cands) < 2:
            return
        k = min(4, len(cands))
        picks = [cands[round(j * (len(cands) - 1) / (k - 1))] for j in range(k)]
        # latest rows first: their drift since is the smallest, so their lines are short,
        # and every one sharpens the velocity that sizes the next one's lines
        picks.sort(key=lambda o: -self.belief.seen[o.id].t)
        rows = []
        params = self.filter.params
        for o in picks:
            found = yield from self._locate(o.id)
            if found is None:
                continue
            body, cov, t, _ = found
            # o(t) - o(τ) less the creep the moves made so far are modelled to cause
            z = np.asarray(body.at) - self.origin - np.asarray(o.at) - self.filter.creep.offset(t - self.epoch)
            rows.append((o.id, body, cov, t, z, t - self.belief.seen[o.id].t))
            dts = np.array([r[5] for r in rows])
            zs = np.array([r[4] for r in rows])
            v = (zs * dts[:, None]).sum(axis=0) / float((dts ** 2).sum())
            resid = zs - dts[:, None] * v[None, :]
            var = (float(np.mean(resid ** 2)) if len(rows) > 2 else 25.0) + 4.0
            var_v = var / float((dts ** 2).sum())
            self.filter = DriftFilter(params, epoch=self.epoch, x0=np.array([0.0, 0.0, v[0], v[1]]),
                                      P0=np.diag([4.0, 4.0, var_v, var_v]))
            for t_move, step in self.move_log:
                self.filter.record_move(t_move, step)
        if not rows:
            return
        for oid, body, cov, t, _, _ in rows:
            self._observe(oid, self._layout(body, t).at, t, cov)
        v = self.filter.x[2:]
        yield Msg("event", (f"drift from the full scan's skew: {v[0]:+.3f}, {v[1]:+.3f} nm/s "
                            f"(+/- {math.sqrt(self.filter.P[2, 2]):.3f}) from {len(rows)} objects",))
        self._log_drift(rows[-1][3])
        yield from self._emit_drift(rows[-1][3])

    def _lift(self):
        """Stop a push: lift the tip straight up within the slew limit."""
        from nanoasm.world.instrument import ramp

        cfg = self.config
        here = yield Msg("position")
        up = np.asarray(here).copy()
        up[2] = cfg.nm_to_codes(np.array([0.0, 0.0, cfg.lift]))[2]
        path = ramp(here, up, cfg)
        if len(path):
            block = yield Msg("write", (path,))
            self.times["travel"] += len(block) / cfg.sample_rate

    def _after(self, op: Operation, start: Body):
        """Local scan after a push: where did the object go? (layout pose, cov, t) or None."""
        o = self.belief[op.object]
        t = yield Msg("clock")
        off = self.offset(t)
        r_max = self.r_max(t, op.object) + 0.1 * math.dist(start.at, op.expect.at)
        a = np.asarray(op.tip_path[0])
        b = np.asarray(op.tip_path[-1])
        delta = float(np.linalg.norm(b - a))
        u = (b - a) / delta if delta > 0 else np.array([1.0, 0.0])
        if o.kind == "rod":
            pattern = rod_after(np.asarray(start.at) + off, start.angle, o.length, o.diameter,
                                b - u * delta / 2 + off, u, delta, r_max,
                                predicted=np.asarray(op.expect.at) + off,
                                predicted_angle=op.expect.angle, options=self.scan_opts)
        else:
            move = np.asarray(op.expect.at) - np.asarray(start.at)
            length = float(np.linalg.norm(move))
            direction = move / length if length > 0 else u
            pattern = particle_after(np.asarray(start.at) + off, o.diameter, direction, length, r_max,
                                     options=self.scan_opts)
        res = yield from self._scan(pattern)
        if not res.found:
            return None
        t = self._scan_ref if self._scan_ref is not None else (yield Msg("clock"))
        centre = np.asarray(res.centre, float) - self.offset(t)
        if self._someone_else(op.object, centre, expected=np.asarray(op.expect.at, float)):
            return None                  # the lines found a neighbour, not the pushed object
        angle = res.angle if o.kind == "rod" and res.angle is not None else o.angle
        body = Body(o.id, o.kind, (float(centre[0]), float(centre[1])), o.diameter,
                    angle if o.elongated else None, o.length if o.elongated else None)
        return body, np.asarray(res.cov if res.cov is not None else np.eye(2) * 4.0), t

    def push(self, op: Operation):
        """One push with its scans; returns "ok", "failed" or "lost"."""
        opts = self.options
        obj_id = op.object
        start = self.belief[obj_id]
        if self.strategy.scans:
            yield from self._reference(start.at, obj_id)
            found = yield from self._locate(obj_id)
            if found is None:
                self.belief.lose(obj_id)
                self.failures.append((obj_id, "lost"))
                yield Msg("event", (f"{obj_id} lost: not found within {opts.lost_radius:.0f} nm",),
                          {"level": "error"})
                return "lost"
            measured, cov, t, _ = found
            if not self._drift_measurement(obj_id, measured, cov, t):
                yield Msg("event", (f"{obj_id} moved on its own",), {"level": "warn"})
            yield from self._emit_drift(t)
            measured = self._layout(measured, t)       # with the drift as now estimated
            self._observe(obj_id, measured.at, t, cov, angle=measured.angle)
            start = self.belief[obj_id]
            if start.kind == "rod":
                at, angle = self._plan_start.get(op.id, (start.at, start.angle))
                expected = Body(obj_id, "rod", at, start.diameter, angle, start.length)
                op = rod_push(op, expected, start)
            else:
                op = particle_push(op, start.at, start.radius, self.plan_options.tip_radius,
                                   self.plan_options.lead)
                if op is None:
                    return "ok"
        verdict = yield from self._stream(op)
        self.counts["pushes"] += 1
        if obj_id not in self.pushed:
            self.pushed.append(obj_id)
        self.belief.expect(obj_id, op.expect.at, op.expect.angle)
        if verdict.failed:
            self.counts["failed_pushes"] += 1
            self.failures.append((obj_id, verdict.status))
            yield Msg("event", (f"push of {obj_id} {verdict.status} (peak force {verdict.peak_force:.0f} nN)",),
                      {"level": "warn"})
        if self.strategy.scans:
            after = yield from self._after(op, start)
            if after is None:
                located = yield from self._locate(obj_id)
                if located is None:
                    self.belief.lose(obj_id)
                    self.failures.append((obj_id, "lost"))
                    return "lost"
                scanner, cov, t = located[:3]
                after = (self._layout(scanner, t), cov, t)
            body, cov, t = after
            self._observe(obj_id, body.at, t, cov, angle=body.angle)
            planned = math.dist(start.at, op.expect.at)
            if not verdict.failed and planned > 20.0 and math.dist(start.at, body.at) < 0.25 * planned:
                # the signals missed it, the scans did not: the tip went over the object
                verdict = Verdict("slipped", None, verdict.peak_force)
                self.counts["failed_pushes"] += 1
                self.failures.append((obj_id, "slipped"))
                yield Msg("event", (f"push of {obj_id} left it where it was: slipped over",), {"level": "warn"})
            if verdict.status == "slipped":
                self.preload_factor[obj_id] = min(self.preload_factor.get(obj_id, 1.0) * 1.6, 4.0)
        t_end = yield Msg("clock")
        yield Msg("emit", ("push", {"op": op.to_dict(), "verdict": verdict.status, "t": t_end,
                                    "offset": [float(v) for v in self.offset(t_end)],
                                    "before": [float(v) for v in start.at],
                                    "peak_force": verdict.peak_force,
                                    "belief": self.belief[obj_id].to_dict()}))
        return "failed" if verdict.failed else "ok"

    # -- the run --------------------------------------------------------------------
    def procedure(self, config) -> Procedure:
        """The whole run as a generator of messages (``config``: the instrument's)."""
        self.config = config
        t_wall = time.perf_counter()
        region_side = max(self.layout.area)
        pixels = int(math.ceil(region_side / self.options.pixel_size))
        # the working area is scanned centred in the scanner's range; its lower-left corner
        # is the layout frame's origin
        self.origin = origin = 0.5 * (np.asarray(config.xy_range, float) - region_side)
        # the layout frame is the scanner frame at the start: drift is measured from here
        self.epoch = epoch = yield Msg("clock")
        if self.strategy.kalman:
            o = self.options
            self.filter = DriftFilter(DriftFilterParams(q=o.drift_q, q_offset=o.drift_q_offset,
                                                        offset_std=1.0), epoch=epoch)
        yield from self._travel_to(origin + region_side / 2)
        t0 = yield Msg("clock")
        yield Msg("event", (f"full scan {pixels} x {pixels} px of {region_side:g} nm",))
        region = (float(origin[0]), float(origin[1]), float(origin[0] + region_side),
                  float(origin[1] + region_side))
        image = yield Msg("full_scan", (pixels, region))
        image = replace(image, origin=(image.origin[0] - origin[0], image.origin[1] - origin[1]))
        t1 = yield Msg("clock")
        yield Msg("emit", ("full_scan", {"t": t1, "height": image.height, "pixel_size": image.pixel_size,
                                         "origin": image.origin}))
        self.times["full_scan"] += t1 - t0
        w0 = time.perf_counter()
        env = identify(image, tip_radius=self.plan_options.tip_radius)
        env = Environment(self.layout.area, env.objects, env.obstacles, env.source)
        self.wall["identify"] = time.perf_counter() - w0
        yield Msg("emit", ("environment", env.to_dict()))
        self.belief = Belief(env, epoch)
        # rows are acquired bottom to top, one every line time: when each object was seen
        line_time = (t1 - t0) / pixels
        for o in env.objects:
            row = min(max(o.at[1] / (region_side / pixels), 0.0), pixels - 1.0)
            self.belief.seen[o.id].t = t0 + (row + 0.5) * line_time
        self.raw = {o.id for o in env.objects}
        self.first_seen = {o.id: (np.asarray(o.at, float), self.belief.seen[o.id].t) for o in env.objects}
        if self.filter is not None:
            # the drift velocity first: the plan needs the objects where they are, not
            # where the full scan's rows put them (hundreds of nm apart over a frame)
            yield from self._bootstrap()
        w0 = time.perf_counter()
        plan = self.replanner.start(self._environment())
        self.wall["plan"] += time.perf_counter() - w0
        first_plan = plan
        yield Msg("emit", ("plan", plan.to_dict()))
        yield Msg("event", (f"plan: {len(plan.assignment)} slot(s) assigned, {len(plan.operations)} push(es)",))
        if self.strategy.anchored:
            self._choose_anchor(plan)
        ops = list(plan.operations)
        self.moving = {op.object for op in ops}
        self._plan_start = self._starts(self._environment(), ops)
        self.env, self.first_plan = env, first_plan
        self.wall["execute"] += time.perf_counter() - t_wall - self.wall["identify"] - self.wall["plan"]
        return (yield from self._execute(ops, 0, 0, {}))

    def resume(self, config, state: dict) -> Procedure:
        """Go on with a run from a checkpoint's ``state`` (see :meth:`state_dict`) on the
        same instrument: no full scan, no new plan; the next push scans its object before
        it as every push does, the drift filter's uncertainty having grown with the time
        the run stood still."""
        self.config = config
        ops, done, corrections = self._restore(state)
        t = yield Msg("clock")
        yield Msg("event", (f"resumed from the checkpoint after push {self.counts['pushes']} "
                            f"({t - float(state['t']):.0f} s later): {len(ops)} push(es) remain",))
        return (yield from self._execute(ops, 0, done, corrections))

    def _execute(self, ops: list[Operation], i: int, done: int, corrections: dict[str, int]) -> Procedure:
        """The pushes of ``ops`` from ``i`` on, with scans, corrections and replanning;
        a checkpoint after each."""
        env, first_plan = self.env, self.first_plan
        w_start, plan0 = time.perf_counter(), self.wall["plan"]
        while i < len(ops):
            op = ops[i]
            if op.object in self.belief.lost:
                i += 1
                continue
            outcome = yield from self.push(op)
            i += 1
            done += 1
            off, limit = 0.0, math.inf
            if self.strategy.scans:
                lost = outcome == "lost"
                off = math.inf if lost else math.dist(self.belief[op.object].at, op.expect.at)
                # a rod's pushes scatter more (pivot, path): re-aiming absorbs up to L/4
                o = self.belief[op.object]
                limit = max(self.options.replan_after, o.length / 4) if o.kind == "rod" else self.options.replan_after
            # an object whose pushes fail, or leave it far off course, again and again
            # (stuck, or against something nobody sees) is not pushed for ever; a rod's
            # course is replanned as a matter of course (its pushes scatter), so for a rod
            # only failed pushes count
            astray_push = outcome == "ok" and off > limit and self.belief[op.object].kind != "rod"
            if outcome == "failed" or astray_push:
                self.troubles[op.object] = self.troubles.get(op.object, 0) + 1
                if self.troubles[op.object] == self.options.max_failures:
                    self.given_up.add(op.object)
                    yield Msg("event", (f"gave up on {op.object} after {self.troubles[op.object]} pushes "
                                        f"failed or went astray: it stays where it is, an obstacle "
                                        f"to the rest",), {"level": "warn"})
            if self.strategy.scans:
                astray = o.kind == "rod" and not lost and not self._course_clear(op.object, ops[i:])
                if lost or (self.strategy.replans and (outcome == "failed" or off > limit or astray)):
                    w0 = time.perf_counter()
                    rest = self.replanner.remainder(self._environment(), done, force=True)
                    self.wall["plan"] += time.perf_counter() - w0
                    self.counts["replans"] += 1
                    ops, i, done = list(rest.plan.operations), 0, 0
                    self._plan_start = self._starts(self._environment(), ops)
                    self.moving = {o.object for o in ops}
                    why = ("lost" if lost else f"{off:.0f} nm off course"
                           + (", its course now too close to a neighbour" if astray else ""))
                    yield Msg("event", (f"replanned after {op.object} {outcome} ({why}): "
                                        f"{len(ops)} push(es) remain",))
                elif op.target is not None and all(o.object != op.object for o in ops[i:]):
                    extra = self._correction(op, corrections)
                    if extra:
                        ops[i:i] = extra
                        self._plan_start.update(self._starts(self._environment(), extra))
            t_now = yield Msg("clock")
            yield Msg("checkpoint", (self._checkpoint(ops, i, done, corrections, t_now),))
        self.wall["execute"] += time.perf_counter() - w_start - (self.wall["plan"] - plan0)
        yield Msg("emit", ("result", _result_doc(self._summary(env, first_plan))))
        return self._summary(env, first_plan)

    def _course_clear(self, obj_id: str, rest: list[Operation]) -> bool:
        """Whether a rod's next planned poses, carried along by its present deviation
        from the plan (re-aiming keeps that deviation: shift and turn), stay clear of the
        other objects by the tip radius. A rod's pushes scatter by a few nm and degrees;
        along a course planned 30 nm from a neighbour, the deviation adds up until the
        rod touches it (and the scans then cannot tell the two apart)."""
        upcoming = list(itertools.takewhile(lambda p: p.object == obj_id, rest))
        if not upcoming or upcoming[0].id not in self._plan_start:
            return True
        o = self.belief[obj_id]
        (ex, ey), ea = self._plan_start[upcoming[0].id]
        if ea is None or o.angle is None:
            return True
        shift = np.asarray(o.at, float) - (ex, ey)
        turn = math.remainder(o.angle - ea, 180.0)
        others = [b for b in self._environment().objects if b.id != obj_id]
        if not others:
            return True
        cores = np.array([b.geometry() for b in others], dtype=object)
        reach = np.array([b.radius for b in others]) + o.radius + self.plan_options.tip_radius
        tree = shapely.STRtree(cores)
        for p in upcoming:
            at = np.asarray(p.expect.at, float) + shift
            body = Body(obj_id, "rod", (float(at[0]), float(at[1])), o.diameter,
                        (p.expect.angle or 0.0) + turn, o.length)
            g = body.geometry()
            idx = tree.query(g, predicate="dwithin", distance=float(reach.max()))
            if idx.size and (shapely.distance(g, cores[idx]) < reach[idx]).any():
                return False
        return True

    def _starts(self, env: Environment, ops: list[Operation]) -> dict[int, tuple]:
        """Pose ``(at, angle)`` the plan expects each operation's object to start from."""
        pose = {o.id: (o.at, o.angle) for o in env.objects}
        out = {}
        for op in ops:
            out[op.id] = pose.get(op.object, (op.expect.at, op.expect.angle))
            pose[op.object] = (op.expect.at, op.expect.angle)
        return out

    def _correction(self, op: Operation, used: dict[str, int]) -> list[Operation]:
        """Pushes that bring an object that missed its slot back in (single-object plan)."""
        target = self.layout.target(op.target)
        o = self.belief[op.object]
        if in_slot(target, o, _tight(self.layout)) or used.get(o.id, 0) >= self.options.max_corrections:
            return []
        used[o.id] = used.get(o.id, 0) + 1
        solo = replace(self.layout, targets=(target,), tolerance=_tight(self.layout))
        # the other objects are only in the way here: no confidence, never assigned
        others = tuple(replace(b, confidence=0.0) for oid, b in self.belief.objects.items()
                       if oid != o.id and oid not in self.belief.lost)
        env = Environment(self.belief.area, (o, *others), self.belief.obstacles)
        from nanoasm.planner import plan_assembly

        plan, _ = plan_assembly(solo, env, self.plan_options)
        self.counts["replans"] += 1
        base = 10_000 * (used[o.id] + 1) + op.id * 10
        return [replace(p, id=base + k) for k, p in enumerate(plan.operations) if p.object == o.id]

    def _choose_anchor(self, plan: Plan) -> None:
        """The anchor: a particle no operation moves, far from the action."""
        moving = {op.object for op in plan.operations}
        cands = [o for o in self.belief.objects.values()
                 if o.id not in moving and o.kind == "particle" and not o.edge]
        if not cands:
            return
        cx, cy = self.layout.area[0] / 2, self.layout.area[1] / 2
        best = min(cands, key=lambda o: (math.dist(o.at, (cx, cy)), o.id))
        self.anchor = (best.id, best.at)

    def _checkpoint(self, ops: list[Operation], i: int, done: int, corrections: dict[str, int],
                    t: float) -> dict:
        return {"t": t, "remaining": [o.to_dict() for o in ops[i:]], "belief": self.belief.to_dict(),
                "counts": dict(self.counts), "times": dict(self.times), "pushed": list(self.pushed),
                "drift": self.drift_log[-1] if self.drift_log else None,
                "state": self.state_dict(ops[i:], done, corrections, t)}

    def state_dict(self, remaining: list[Operation], done: int, corrections: dict[str, int],
                   t: float) -> dict:
        """Everything :meth:`resume` needs to go on after ``done`` operations of the
        current plan, ``remaining`` to run (JSON types, lossless)."""
        def plan_doc(plan: Plan | None, ops=None) -> dict | None:
            if plan is None:
                return None
            return (replace(plan, operations=tuple(ops)) if ops is not None else plan).to_dict()

        return {
            "format": "nanoasm.checkpoint/1", "t": t, "saved_at": time.time(), "strategy": self.strategy.value,
            "epoch": self.epoch, "origin": [float(v) for v in self.origin],
            "env": self.env.to_dict(), "first_plan": plan_doc(self.first_plan),
            "plan": plan_doc(self.replanner.plan), "base": (self.replanner.base.to_dict()
                                                            if self.replanner.base is not None else None),
            "remaining": plan_doc(self.first_plan, remaining), "done": done,
            "corrections": dict(corrections), "belief": self.belief.state_dict(),
            "filter": self.filter.state_dict() if self.filter is not None else None,
            "raw": sorted(self.raw), "first_seen": {k: [float(a[0]), float(a[1]), float(ts)]
                                                    for k, (a, ts) in self.first_seen.items()},
            "no_reference": sorted(self.no_reference), "pushed": list(self.pushed),
            "troubles": dict(self.troubles), "given_up": sorted(self.given_up),
            "moving": sorted(self.moving), "preload_factor": dict(self.preload_factor),
            "plan_start": {str(k): [list(at), ang] for k, (at, ang) in self._plan_start.items()},
            "creep_anchor": None if self._creep_anchor is None else [float(v) for v in self._creep_anchor],
            "anchor": None if self.anchor is None else [self.anchor[0], list(self.anchor[1])],
            "anchor_offset": [float(v) for v in self.anchor_offset],
            "counts": dict(self.counts), "times": dict(self.times), "wall": dict(self.wall),
            "failures": [list(f) for f in self.failures],
            "drift_log": [list(d) for d in self.drift_log]}

    def _restore(self, st: dict) -> tuple[list[Operation], int, dict[str, int]]:
        """Set the run's state from :meth:`state_dict`; returns (remaining, done, corrections)."""
        from nanoasm.planner.plan import plan_from_dict
        from nanoasm.world.environment import environment_from_dict

        if st.get("format") != "nanoasm.checkpoint/1":
            raise ValueError(f"not a nanoasm checkpoint (format {st.get('format')!r})")
        if st["strategy"] != self.strategy.value:
            raise ValueError(f"the run used strategy {st['strategy']!r}, not {self.strategy.value!r}")
        self.epoch, self.origin = float(st["epoch"]), np.asarray(st["origin"], float)
        self.env = environment_from_dict(st["env"], "checkpoint")
        self.first_plan = plan_from_dict(st["first_plan"], "checkpoint")
        self.replanner.plan = plan_from_dict(st["plan"], "checkpoint") if st["plan"] else None
        self.replanner.base = environment_from_dict(st["base"], "checkpoint") if st["base"] else None
        remaining = list(plan_from_dict(st["remaining"], "checkpoint").operations)
        self.belief = Belief.from_state(st["belief"])
        if st["filter"] is not None:
            o = self.options
            self.filter = DriftFilter.from_state(
                DriftFilterParams(q=o.drift_q, q_offset=o.drift_q_offset, offset_std=1.0), st["filter"])
        self.raw = set(st["raw"])
        self.first_seen = {k: (np.array(v[:2], float), float(v[2])) for k, v in st["first_seen"].items()}
        self.no_reference = set(st["no_reference"])
        self.troubles = {k: int(v) for k, v in st["troubles"].items()}
        self.given_up = set(st["given_up"])
        self.pushed = list(st["pushed"])
        self.moving = set(st["moving"])
        self.preload_factor = {k: float(v) for k, v in st["preload_factor"].items()}
        self._plan_start = {int(k): (tuple(v[0]), v[1]) for k, v in st["plan_start"].items()}
        self._creep_anchor = None if st["creep_anchor"] is None else np.asarray(st["creep_anchor"], float)
        self.anchor = None if st["anchor"] is None else (st["anchor"][0], tuple(st["anchor"][1]))
        self.anchor_offset = np.asarray(st["anchor_offset"], float)
        self.counts.update({k: int(v) for k, v in st["counts"].items()})
        self.times.update({k: float(v) for k, v in st["times"].items()})
        self.wall.update({k: float(v) for k, v in st["wall"].items()})
        self.failures = [tuple(f) for f in st["failures"]]
        self.drift_log = [tuple(d) for d in st["drift_log"]]
        return remaining, int(st["done"]), {k: int(v) for k, v in st["corrections"].items()}

    def _summary(self, env: Environment, first_plan: Plan) -> RunSummary:
        plan = self.replanner.plan or first_plan
        lost = self.belief.lost
        assignment, unfilled = [], list(plan.unfilled)
        for a in plan.assignment:
            if a.object in lost:
                unfilled.append(Unfilled(a.target, f"object {a.object!r} was lost during the run"))
            else:
                assignment.append(a)
        return RunSummary(env, first_plan, self.belief, tuple(assignment), tuple(unfilled), self.pushed,
                          Counts(**self.counts), dict(self.times), dict(self.wall), self.drift_log,
                          self.failures, self.epoch, (float(self.origin[0]), float(self.origin[1])))


def _tight(layout: Layout):
    """Half the layout's tolerance: correct what would be borderline."""
    t = layout.tolerance
    return replace(t, position=t.position * 0.6, angle=t.angle * 0.6)


def _result_doc(s: RunSummary) -> dict:
    """What the run did, for the run log."""
    return {"assignment": [a.to_dict() for a in s.assignment], "unfilled": [u.to_dict() for u in s.unfilled],
            "pushed": list(s.pushed), "counts": dict(vars(s.counts)), "times": dict(s.times),
            "wall": dict(s.wall), "failures": [{"object": o, "cause": c} for o, c in s.failures],
            "epoch": s.epoch, "origin": list(s.origin)}
