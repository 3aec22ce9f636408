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
from nanoasm.planner import Operation, Plan, PlanOptions, Replanner
from nanoasm.planner.assign import in_slot
from nanoasm.planner.plan import Assignment, Unfilled
from nanoasm.world.cantilever import SEED_LEVER, Cantilever
from nanoasm.world.environment import Environment
from nanoasm.world.identify import identify

from .belief import Belief
from .dac import plan_dac
from .drift_steps import DriftSteps
from .engine import Msg
from .monitor import PushMonitor, Verdict
from .reaim import particle_push, rod_push
from .report import Counts
from .run_state import RunState
from .scan_lines import ScanOptions
from .scan_steps import ScanSteps
from .strategy import ExecOptions
from .trajectory import PUSH, TRAVEL, operation

Procedure = Generator[Msg, Any, "RunSummary"]
ACTIVITIES = ("full_scan", "local_scan", "push", "travel")


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


class Assembly(DriftSteps, ScanSteps, RunState):
    """State and steps of one unattended assembly run (see the module docstring); the drift
    estimate, the local scans and the checkpoint state are in its mixins
    (:mod:`~nanoasm.executor.drift_steps`, :mod:`~nanoasm.executor.scan_steps`,
    :mod:`~nanoasm.executor.run_state`)."""

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
        self.scan_opts = ScanOptions(spacing=self.options.scan_spacing)
        self.raw: set[str] = set()
        self.moving: set[str] = set()            # objects the current plan still moves
        self._plan_start: dict[int, tuple] = {}  # pose each operation expects to start from
        self.preload_factor: dict[str, float] = {}
        self.move_log: list[tuple[float, np.ndarray]] = []
        self._creep_anchor: np.ndarray | None = None   # where the last recorded move ended, nm
        self._scan_ref: float | None = None   # time of the running pattern's first line
        self.epoch = 0.0
        self.origin = np.zeros(2)

    # -- the planner's view -------------------------------------------------------------
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

    # -- documents for the run log (emitted; subscribers such as RunLog keep them) -----
    def _dac_doc(self, codes, kind, block, every: int = 50) -> dict:
        """A streamed DAC chunk, every ``every``-th sample: scanner nm, kind, signals."""
        nm = self.config.codes_to_nm(np.asarray(codes)[::every])
        return {"t": block.t[::every].tolist(), "x": nm[:, 0].tolist(), "y": nm[:, 1].tolist(),
                "z": nm[:, 2].tolist(), "kind": np.asarray(kind)[::every].tolist(),
                "s_n": block.s_n[::every].tolist(), "s_l": block.s_l[::every].tolist(),
                "n": int(len(codes)), "every": every}

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
                    now = self._environment()
                    rest = self.replanner.remainder(now, done, force=True)
                    self.wall["plan"] += time.perf_counter() - w0
                    self.counts["replans"] += 1
                    ops, i, done = list(rest.plan.operations), 0, 0
                    self._plan_start = self._starts(now, ops)
                    self.moving = {o.object for o in ops}
                    why = ("lost" if lost else f"{off:.0f} nm off course"
                           + (", its course now too close to a neighbour" if astray else ""))
                    yield Msg("event", (f"replanned after {op.object} {outcome} ({why}): "
                                        f"{len(ops)} push(es) remain",))
                    yield Msg("emit", ("plan", rest.plan.to_dict()))
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
