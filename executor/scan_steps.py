"""The local scans of an assembly run: patterns through scan_line messages, before and after
a push, and the widening search.

A mixin of :class:`~nanoasm.executor.assembly.Assembly` (its state lives there).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from nanoasm.bodies import Body
from nanoasm.planner import Operation

from .engine import Msg
from .local_scan import particle_after, particle_before, rod_after, rod_before
from .lost_search import find_lost_particle

#: A scan line starting farther than this (nm) from the tip is preceded by a travel.
APPROACH = 300.0


class ScanSteps:
    """Local scans and lifted travel of an :class:`Assembly`."""

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

    def _line_doc(self, a, b, heights, t: float) -> dict:
        """A local-scan line: end points (scanner frame), heights, and the scanner position
        of the layout origin as estimated then (layout = scanner - offset)."""
        off = self.offset(t if self.filter is None else max(t, self.filter.time))
        return {"t": t, "a": [float(a[0]), float(a[1])], "b": [float(b[0]), float(b[1])],
                "heights": np.asarray(heights, float).tolist(), "offset": [float(off[0]), float(off[1])]}

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

    def _approach(self, xy):
        """Travel (lifted, recorded for creep) to a scan line that starts far from the tip,
        so the scan itself is a small move."""
        here = yield Msg("position")
        there = self.config.codes_to_nm(np.asarray(here))[:2]
        if math.dist(there, xy) > APPROACH:
            lo, hi = self.config.lower[:2], self.config.upper[:2]
            yield from self._travel_to(np.clip(np.asarray(xy, float), lo, hi))

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
