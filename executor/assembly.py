"""The assembly procedure: full scan -> identify -> plan -> for every push: reference scans,
a local scan before, the push streamed with drift folded in and its signals watched, a
local scan after, corrections or replanning -> checkpoint.

It is a generator of :class:`~nanoasm.executor.engine.Msg` run by the
:class:`~nanoasm.executor.engine.RunEngine`; it never touches an instrument (nor a
simulated truth) itself. Its state is in components, each with ``state_dict()``: the
drift estimator (:mod:`.estimators`), the belief, the full scan's references
(:mod:`.references`), the ledger (:mod:`.ledger`) and the course (:mod:`.course`); its
scans and moves are plan stubs (:mod:`.scan_steps`, :mod:`.motion_steps`,
:mod:`.drift_steps`, :mod:`.drift_bootstrap`). Frames: the plan and the belief are in the layout frame (the frame
of the first full scan); a layout point ``p`` is at ``p + offset(t)`` in the scanner frame.
A layout with alignment marks is registered to that scan once the drift is bootstrapped
and mapped into its frame (``_register``); the first plan carries the transform.
"""

from __future__ import annotations

import time
from collections.abc import Generator
from dataclasses import replace
from typing import Any

import numpy as np

from nanoasm.cad.layout import Layout
from nanoasm.planner import Operation, PlanOptions, Replanner
from nanoasm.planner.alignment import in_scan_frame
from nanoasm.world.cantilever import SEED_LEVER, Cantilever
from nanoasm.world.environment import Environment
from nanoasm.world.identify import identify

from .baselines import BaselineMaps
from .belief import Belief
from .context import RunContext
from .course import Course
from .progress_docs import PROGRESS, ProgressDoc
from .drift_bootstrap import bootstrap
from .drift_steps import unskewed_obstacles
from .engine import Msg
from .keepout_frame import KeepoutWitness
from .estimators import estimator_for
from .motion_steps import travel_to
from .after_push import correct, review, shoved_back
from .batching import push_together, together
from .pushing import push
from .landmarks import Landmarks, moved_area
from .lever_file import lever_line
from .references import References
from .repair import repair_round
from .reviewed_plan import ReviewedPlan, first_plan
from .scan_area import ScanArea
from .checkpoints import checkpoint, restore
from .strategy import ExecOptions
from .summary import RunSummary, summary
from .torn_band import survey_band
from .verdict import final_check

Procedure = Generator[Msg, Any, RunSummary]


def _phase(name: str) -> Msg:
    """The message telling progress displays that the run enters phase ``name``."""
    return Msg("emit", (PROGRESS, ProgressDoc("phase", name)))


class Assembly:
    """One unattended assembly run (see the module docstring): the procedure, composed of
    its components; :meth:`procedure` starts afresh, :meth:`resume` goes on from a
    checkpoint."""

    def __init__(self, layout: Layout, options: ExecOptions | None = None,
                 plan_options: PlanOptions | None = None, *, lever: Cantilever = SEED_LEVER,
                 source: str | None = None, baselines: BaselineMaps | None = None,
                 reviewed: ReviewedPlan | None = None, scan: ScanArea | None = None):
        self.layout = layout                     # in the scan's frame once registered (_register)
        self.source = source                     # the layout's file, named by a failed registration
        self.reviewed, self.scan = reviewed, scan    # a plan to start from; the full scan (None: centred)
        self.options = options or ExecOptions()
        self.plan_options = plan_options or PlanOptions()
        self.strategy = self.options.strategy
        self.lever = lever                       # the compensation's constants (the instrument's, calibrated)
        self.baselines = baselines               # the detector's A(i, j), B(i, j); None: free air per push
        self.replanner = Replanner(layout, self.plan_options)
        self.course = Course()
        self.ctx: RunContext | None = None       # set when the run starts or resumes
        self.env: Environment | None = None      # identified by the first full scan
        self.first_plan = None
        self.slots: tuple = ()                   # the verdict of the final check scans
        self.recheck: set[str] | None = None     # the slots the next check scans (None: all)

    # -- the run --------------------------------------------------------------------
    def procedure(self, config) -> Procedure:
        """The whole run as a generator of messages (``config``: the instrument's)."""
        t_wall = time.perf_counter()
        # the working area (by default centred in the scanner's range): its lower-left corner
        # is the layout frame's origin, and the scanner frame at the start is the layout
        # frame: drift is measured from here
        area = self.scan or ScanArea.centred(self.layout.area, config.xy_range, self.options.pixel_size)
        region_side, pixels, origin = area.side, area.pixels, np.asarray(area.origin, float)
        epoch = yield Msg("clock")
        drift = estimator_for(self.strategy, origin, epoch, self.options)
        ctx = self.ctx = RunContext(config, self.options, drift, None, References(), baselines=self.baselines)
        yield Msg("event", (lever_line(self.lever, self.baselines),))
        yield from travel_to(ctx, origin + region_side / 2)
        t0 = yield Msg("clock")
        yield _phase("full scan")
        yield Msg("event", (f"full scan {pixels} x {pixels} px of {region_side:g} nm",))
        image = yield Msg("full_scan", (pixels, area.region))
        image = replace(image, origin=(image.origin[0] - origin[0], image.origin[1] - origin[1]))
        t1 = yield Msg("clock")
        yield Msg("emit", ("full_scan", {"t": t1, "height": image.height, "pixel_size": image.pixel_size,
                                         "origin": image.origin}))
        ledger = ctx.ledger
        ledger.times["full_scan"] += t1 - t0
        yield _phase("identify")
        w0 = time.perf_counter()
        env = identify(image, tip_radius=self.plan_options.tip_radius)
        env = Environment(self.layout.area, env.objects, env.obstacles, env.source)
        ledger.wall["identify"] = time.perf_counter() - w0
        yield Msg("emit", ("environment", env.to_dict()))
        ctx.belief = Belief(env, epoch)
        # rows are acquired bottom to top, one every line time: when each object was seen
        line_time = (t1 - t0) / pixels
        for o in env.objects:
            row = min(max(o.at[1] / (region_side / pixels), 0.0), pixels - 1.0)
            ctx.belief.seen[o.id].t = t0 + (row + 0.5) * line_time
        ctx.refs = References.of_scan(env.objects, ctx.belief.seen)
        ctx.full_scan, ctx.env_objects = image, env.objects
        if drift.uses_landmarks:
            ctx.landmarks = Landmarks.of_scan(image, env.obstacles, (t0, line_time))
            yield Msg("event", (f"{len(ctx.landmarks.features)} fixed feature(s) of the obstacles "
                                f"as drift references",))
        # the drift velocity first: the plan needs the objects where they are, not where
        # the full scan's rows put them (hundreds of nm apart over a frame)
        if drift.bootstraps:
            yield _phase("drift")
        def row_time(y: float) -> float:
            return t0 + (min(max(y * pixels / region_side, 0.0), pixels - 1.0) + 0.5) * line_time

        keep = None if self.layout.marks or self.plan_options.align == "none" else \
            KeepoutWitness(self.layout, env.obstacles, row_time, area.resolution)
        yield from bootstrap(ctx, keep)
        yield from self._register(env, row_time, area.resolution)
        # the obstacles too (electrodes: a slot beside one is planned against where it is)
        ctx.belief.obstacles = unskewed_obstacles(env.obstacles, drift, row_time)
        if self.strategy.scans:                # a band a jump made the full scan skip, if a particle is missing
            yield from survey_band(ctx, self.layout, t0, line_time, pixels, region_side,
                                   self.plan_options.tip_radius)
        yield _phase("plan")
        w0 = time.perf_counter()
        plan, line = first_plan(self.replanner, self.reviewed, self.layout, self.ctx.environment(), area.pixel_size)
        ledger.wall["plan"] += time.perf_counter() - w0
        yield Msg("emit", ("plan", plan.to_dict()))
        yield Msg("event", (line,))
        drift.after_plan(plan, ctx.belief, self.layout.area)
        ops = list(plan.operations)
        ctx.moving = {op.object for op in ops}
        if drift.uses_landmarks:
            ctx.landmarks.choose_windows(image, self.options.relocalise_window,
                                         avoid=moved_area(env, ops, self.layout))
        self.course.follow(self.ctx.environment(), ops)
        self.env, self.first_plan = env, plan
        yield _phase("execute")
        ledger.wall["execute"] += time.perf_counter() - t_wall - ledger.wall["identify"] - ledger.wall["plan"]
        return (yield from self._execute(ops, 0, 0, {}))

    def _register(self, env: Environment, row_time, resolution: float) -> Procedure:
        """A layout with marks registered to the obstacles of the full scan, each corner
        moved by the drift of its row's time (``row_time(y)``; known once the drift is
        bootstrapped): from here on the run works in the scan's frame
        (:func:`~nanoasm.planner.alignment.in_scan_frame`; a failure is one InputError
        naming the layout's file)."""
        drift = self.ctx.drift

        def unskewed(p) -> tuple[float, float]:
            x, y = drift.unskew(np.asarray(p, float), row_time(p[1]) - drift.epoch)
            return float(x), float(y)

        layout, alignment = in_scan_frame(self.layout, env, self.plan_options.align, moved=unskewed,
                                          resolution=resolution, source=self.source)
        if alignment is not None:
            self.registered(alignment.transform, layout)
            yield Msg("event", (alignment.line(),))
            yield Msg("emit", ("registration", alignment.to_doc()))

    def registered(self, transform, layout: Layout | None = None) -> None:
        """Work in the scan's frame from here on: the layout mapped by ``transform`` (the
        registration of its marks; ``layout``, when given, is the layout so mapped)."""
        if transform is None or self.layout.registration is not None:
            return
        self.layout = layout if layout is not None else self.layout.mapped(transform, self.layout.area)
        self.replanner = Replanner(self.layout, self.plan_options)

    def resume(self, config, state: dict) -> Procedure:
        """Go on with a run from a checkpoint's ``state`` (see :func:`.checkpoints.checkpoint`)
        on the same instrument: no full scan, no new plan; the next push scans its object
        before it as every push does, the drift estimate's uncertainty having grown with
        the time the run stood still."""
        ops, done, corrections = restore(self, config, state)
        self.ctx.baselines = self.baselines
        yield _phase("execute")
        t = yield Msg("clock")
        self.ctx.drift.resumed(t - float(state["t"]))
        if state.get("checked") is not None:        # after the last check scans: their verdict stands
            yield Msg("event", (f"resumed from the checkpoint after the check scans ({t - float(state['t']):.0f} s "
                                f"later): the run's result as they left it",))
            return (yield from self._result())
        yield Msg("event", (f"resumed from the checkpoint after push {self.ctx.ledger.counts['pushes']} "
                            f"({t - float(state['t']):.0f} s later): {len(ops)} push(es) remain",))
        return (yield from self._execute(ops, 0, done, corrections))

    def _execute(self, ops: list[Operation], i: int, done: int, corrections: dict[str, int]) -> Procedure:
        """The pushes of ``ops`` from ``i`` on, then the check scans of every slot; while
        slots are not filled and repair rounds remain, a survey of them and the pushes
        planned from it (:mod:`.repair`), checked again."""
        while True:
            done = yield from self._pushes(ops, i, done, corrections)
            yield from final_check(self)        # the verdict: what scans find, not the belief
            ops, i, done = (yield from repair_round(self, done)), 0, 0
            if not ops:
                break
        t_now = yield Msg("clock")                     # the belief as the check scans left it
        yield Msg("checkpoint", (checkpoint(self, [], done, corrections, t_now, checked=self.slots),))
        return (yield from self._result())

    def _result(self) -> Procedure:
        """The run's result (:func:`.summary.summary`), emitted and returned."""
        result = summary(self)
        yield Msg("emit", ("result", result.to_doc()))
        return result

    def _pushes(self, ops: list[Operation], i: int, done: int, corrections: dict[str, int]):
        """The pushes of ``ops`` from ``i`` on, with scans, corrections and replanning;
        a checkpoint after each (after each group of pushes made in one contact phase,
        :mod:`.batching`). Returns how many of the current plan's ran."""
        ctx = self.ctx
        mark = (time.perf_counter(), ctx.ledger.wall["plan"])
        while i < len(ops):
            op = ops[i]
            if op.object in ctx.belief.lost:
                i += 1
                continue
            n = together(ctx, ops, i, self.plan_options)
            group = ops[i:i + n]
            if n == 1:
                outcomes = [(yield from push(ctx, op, self.course, self.lever, self.plan_options))]
            else:
                outcomes = yield from push_together(ctx, group, self.course, self.lever, self.plan_options)
            i += n
            done += n
            why = None
            for op, outcome in zip(group, outcomes):
                reason = yield from review(self, op, outcome, ops, i)
                why = why or reason
            if why is not None:
                ops, i, done = (yield from self.replan(done, why)), 0, 0
            elif self.strategy.scans:
                for op in group:
                    if op.target is not None and all(p.object != op.object for p in ops[i:]):
                        correct(self, op, ops, i, corrections)
            if ctx.shoved:
                shoved_back(self, ops, i, corrections)
            mark = self._count_execute(mark)        # the checkpoint holds the compute so far
            t_now = yield Msg("clock")
            yield Msg("checkpoint", (checkpoint(self, ops[i:], done, corrections, t_now),))
        self._count_execute(mark)
        return done

    def _count_execute(self, mark: tuple[float, float]) -> tuple[float, float]:
        """Add the wall time since ``mark`` (``perf_counter()`` and the plan stage's seconds
        then), less what planning took meanwhile, to the execute stage; returns the new mark.
        A checkpoint so holds the run's compute up to it, to which a resumed run adds its own."""
        wall = self.ctx.ledger.wall
        now = time.perf_counter()
        wall["execute"] += now - mark[0] - (wall["plan"] - mark[1])
        return now, wall["plan"]

    def replan(self, done: int, after: str):
        """Plan what remains from the present belief (``after``: what made it needed, for
        the event); returns its operations."""
        ctx = self.ctx
        w0 = time.perf_counter()
        now = self.ctx.environment()
        before = {a.target for a in (self.replanner.plan.assignment if self.replanner.plan else ())}
        rest = self.replanner.remainder(now, done, force=True, pivot_offsets=ctx.pivots.offsets(now.objects))
        ctx.ledger.wall["plan"] += time.perf_counter() - w0
        ctx.ledger.counts["replans"] += 1
        ops = list(rest.plan.operations)
        self.course.follow(now, ops)
        ctx.moving = {p.object for p in ops}
        # a slot the plan had and the new one leaves unfilled is named, with the planner's reason
        dropped = "".join(f"; slot {u.target} left unfilled: {u.reason}" for u in rest.plan.unfilled
                          if u.target in before)
        yield Msg("event", (f"replanned after {after}: {len(ops)} push(es) remain{dropped}",))
        yield Msg("emit", ("plan", rest.plan.to_dict()))
        return ops
