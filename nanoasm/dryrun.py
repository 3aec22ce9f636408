"""Dry-runs: the real executor against the simulated AFM, and the report of what happened.

This harness is the only place that reads the simulated truth (before and after the run,
for the report); the executor itself sees the simulated AFM only through the
``Instrument`` protocol, as it would see hardware.
"""

from __future__ import annotations

import math
import os
import time

import numpy as np
from scipy.optimize import linear_sum_assignment
from dataclasses import dataclass

from nanoasm.bodies import Body
from nanoasm.cad.layout import Layout
from nanoasm.executor.assembly import Assembly
from nanoasm.executor.summary import RunSummary
from nanoasm.executor.engine import RunEngine, Subscriber
from nanoasm.executor.report import InstrumentTime, Report, WallTime
from nanoasm.executor.runlog import RunLog, to_json
from nanoasm.executor.strategy import ExecOptions
from nanoasm.planner import PlanOptions
from nanoasm.planner.plan import Assignment
from nanoasm.planner.assign import in_slot
from nanoasm.simkeep import SimKeeper
from nanoasm.world.scene import Scene
from nanoasm.world.sim import SimulatedAFM


@dataclass(frozen=True)
class Outcome:
    """A dry-run's report plus the figures derived from it."""

    report: Report
    summary: RunSummary
    filled: tuple[str, ...]
    errors: dict[str, float]          # centre error of every assigned slot, nm

    @property
    def rms_error(self) -> float:
        vals = [self.errors[t] for t in self.filled]
        return math.sqrt(sum(v * v for v in vals) / len(vals)) if vals else math.nan


#: The run log's channels of the truth, which this harness alone writes: (topic, schema,
#: what it holds), as :data:`nanoasm.executor.runlog.TOPICS` lists the executor's.
TRUTH_TOPICS = (
    ("/sim/truth", "nanoasm.SimTruth", "dry-runs only, from the harness: true objects before and after"),
    ("/sim/truth/scene", "foxglove.SceneUpdate", "dry-runs only: the true objects after the run"),
)
_TRUTH_COLOUR = (0.8, 0.4, 1.0, 0.9)


def _log_world(log: RunLog, scene: Scene, sim: SimulatedAFM, seed: int) -> None:
    """Open the truth's channels; attach the scene and the simulated instrument's configuration."""
    log.add_channel("/sim/truth", "nanoasm.SimTruth", "simulated truth (harness only)", ("phase", "objects"))
    log.add_channel("/sim/truth/scene", "foxglove.SceneUpdate")
    log.attach("scene.json", scene.dumps_json().encode("utf-8"))
    log.attach("instrument.json", to_json(sim.config))
    log.metadata("dry-run", {"seed": str(seed)})


def _log_truth(log: RunLog, initial: tuple[Body, ...], final: tuple[Body, ...], ids: dict[str, str],
               t: float) -> None:
    """The true objects (layout frame) before and after the run, and which identified object
    each one is (``ids``: identified id -> scene id); then the log is finished."""
    for phase, bodies in (("initial", initial), ("final", final)):
        log.write("/sim/truth", {"phase": phase, "objects": [b.to_dict() for b in bodies], "ids": ids}, t)
    log.write_bodies("/sim/truth/scene", [b.to_dict() for b in final], t, prefix="truth", colour=_TRUTH_COLOUR)
    log.finish()


def _layout_frame(sim: SimulatedAFM, summary: RunSummary, bodies: tuple[Body, ...]) -> tuple[Body, ...]:
    """Truth moved into the layout frame: the scanner frame at the run's start (its
    ``epoch``) less the layout origin the run chose."""
    ox, oy = sim.true_offset(summary.epoch)
    dx, dy = ox - summary.origin[0], oy - summary.origin[1]
    return tuple(Body(b.id, b.kind, (b.at[0] + dx, b.at[1] + dy), b.diameter,
                      None if b.angle is None else b.angle % 180.0, b.length) for b in bodies)


def match_ids(found, truth: tuple[Body, ...], reach: float = 500.0) -> dict[str, str]:
    """Identified object id -> the scene's id of the true object it is.

    A full scan takes minutes, so the objects it shows are shifted by the drift of the
    time their line was recorded (hundreds of nm): they are matched as a whole, by
    ``linear_sum_assignment`` over kind, size and distance, pairs farther than ``reach``
    left out. Objects that identification invented keep their own ids.
    """
    found = list(found)
    if not found or not truth:
        return {}
    cost = np.full((len(found), len(truth)), 1e9)
    for i, o in enumerate(found):
        for j, b in enumerate(truth):
            d = math.dist(o.at, b.at)
            if o.kind == b.kind and d <= reach:
                cost[i, j] = d + 20.0 * abs(o.diameter - b.diameter)
    rows, cols = linear_sum_assignment(cost)
    return {found[i].id: truth[j].id for i, j in zip(rows, cols) if cost[i, j] < 1e9}


def filled_slots(layout: Layout, assignment, final: dict[str, Body]) -> tuple[tuple[str, ...], dict[str, float]]:
    """Slots filled by the report's rule, and each assigned slot's centre error (nm)."""
    tol = layout.tolerance
    filled, errors = [], {}
    used: set[str] = set()
    for a in assignment:
        t, o = layout.target(a.target), final.get(a.object)
        if o is None:
            continue
        errors[t.id] = math.dist(t.at, o.at)
        if in_slot(t, o, tol) and o.id not in used:
            filled.append(t.id)
            used.add(o.id)
    return tuple(filled), errors


def dry_run(scene: Scene, layout: Layout, *, seed: int | None = None,
            options: ExecOptions | None = None, plan_options: PlanOptions | None = None,
            subscribers: list[Subscriber] | None = None, scene_name: str | None = None,
            layout_name: str | None = None, keep_sim: str | os.PathLike | None = None,
            resume: tuple[dict, dict] | None = None) -> Outcome:
    """Run the assembly of ``layout`` on a simulated AFM holding ``scene``.

    ``keep_sim``: keep the simulated world at every checkpoint in this file (for
    resuming; see :mod:`nanoasm.executor.resume`). ``resume``: ``(checkpoint state,
    kept world)`` of a stopped dry-run to go on with instead of starting afresh.
    """
    seed = scene.seed if seed is None else seed
    seed = 0 if seed is None else seed
    t_wall = time.perf_counter()
    if resume is not None:          # the world as the stopped run left it
        state, kept = resume
        sim, start_clock, initial_sample = kept["sim"], kept["start_clock"], kept["initial"]
    else:
        sim = SimulatedAFM(scene, seed=seed)
        start_clock = sim.clock()
        initial_sample = sim.truth()
    assembly = Assembly(layout, options, plan_options)
    subscribers = list(subscribers or ())
    if keep_sim is not None:
        subscribers.append(SimKeeper(keep_sim, sim, {"start_clock": start_clock, "initial": initial_sample}))
    engine = RunEngine(sim, subscribers)
    # run logs get the scene before and the truth after the run, from this harness alone
    logs = [s for s in subscribers if isinstance(s, RunLog)]
    for log in logs:
        _log_world(log, scene, sim, seed)
    procedure = (assembly.resume(sim.config, resume[0]) if resume is not None
                 else assembly.procedure(sim.config))
    summary = engine.run(procedure)
    initial = _layout_frame(sim, summary, initial_sample)
    final = _layout_frame(sim, summary, sim.truth())
    total = sim.clock() - start_clock
    t = summary.times
    ids = match_ids(summary.env.objects, initial)
    for log in logs:
        _log_truth(log, initial, final, ids, sim.clock())
    assignment = tuple(Assignment(a.target, ids.get(a.object, a.object)) for a in summary.assignment)
    report = Report(
        scene=scene_name, layout=layout_name, seed=seed,
        targets=layout.targets, initial_objects=initial, final_objects=final,
        assignment=assignment, pushed=tuple(ids.get(p, p) for p in summary.pushed),
        unfilled=summary.unfilled,
        counts=summary.counts,
        instrument_time=InstrumentTime(t["full_scan"], t["local_scan"], t["push"], t["travel"], total),
        wall_time=WallTime(summary.wall["identify"], summary.wall["plan"], summary.wall["execute"],
                           time.perf_counter() - t_wall),
    )
    filled, errors = filled_slots(layout, report.assignment, {b.id: b for b in final})
    return Outcome(report, summary, filled, errors)

