"""The drift side of an assembly run: the offset estimate and what feeds it.

A mixin of :class:`~nanoasm.executor.assembly.Assembly` (its state lives there): the
layout-to-scanner offset of the strategy, reference objects measured against their
full-scan position, the drift velocity from the full scan's skew, and the scanner moves
that creep (recorded by the chain rule of :mod:`nanoasm.drift.creep`).
"""

from __future__ import annotations

import math

import numpy as np

from nanoasm.bodies import Body
from nanoasm.drift import DriftFilter
from nanoasm.drift.creep import CreepingOffset

from .dac_frames import LinearDrift
from .engine import Msg
from .trajectory import PUSH, TRAVEL

#: A drift reference is chosen at least this far (nm, plus a rod's length) from the push.
REFERENCE_GAP = 300.0
#: Variance (nm² per axis) of an object's position in the first full scan, its row's
#: drift aside (identification measured 0.28 nm on centres; 2 nm covers pixel effects).
FULL_SCAN_VAR = 4.0


class DriftSteps:
    """Drift estimate, references and creep of an :class:`Assembly`."""

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

    def _is_reference(self, obj_id: str) -> bool:
        """Whether an object may measure drift: never pushed, never gated out."""
        return (obj_id in self.first_seen and obj_id not in self.pushed
                and obj_id not in self.no_reference and obj_id not in self.belief.lost)

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
