"""Dry-runs: the real executor against the simulated AFM, and the report of what happened.

This harness is the only place that reads the simulated truth (before and after the run,
for the report and the run log's ``/sim/truth``); the executor itself sees the simulated
AFM only through the ``Instrument`` protocol, as it would see hardware. Its twin for real
runs is :mod:`nanoasm.run`; both report through :func:`nanoasm.harness.report_of`.
:func:`dry_run` runs a scene and a layout; :func:`dry_run_files` and
:func:`resume_dry_run` are the command line's, with the run log, the simulated world
kept beside it for resuming (:mod:`nanoasm.simkeep`) and the report file. A dry-run
first calibrates the simulated instrument's lever (:func:`nanoasm.calibrate.simulated_calibration`)
and compensates with what it measured, as a run compensates with its instrument file's.
"""

from __future__ import annotations

import math
import os
import time
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

from nanoasm.bodies import Body
from nanoasm.cad.layout import Layout, load_layout
from nanoasm.errors import InputError
from nanoasm.calibrate import simulated_calibration
from nanoasm.executor.assembly import Assembly
from nanoasm.executor.calibration import Calibration
from nanoasm.executor.calibration_fit import CalibrationFailed
from nanoasm.executor.documents import as_dict
from nanoasm.executor.checkpoints import checkpoint_batch
from nanoasm.executor.engine import RunEngine, Subscriber
from nanoasm.executor.report import Report
from nanoasm.executor.resume import resume_point, resumed_log_path
from nanoasm.executor.runlog import RunLog, to_json
from nanoasm.executor.strategy import ExecOptions
from nanoasm.executor.summary import RunSummary
from nanoasm.executor.reviewed_plan import ReviewedPlan
from nanoasm.executor.scan_area import ScanArea
from nanoasm.harness import LogTo, own_frame, plain, report_of, run_logs, run_start, warn
from nanoasm.planner import PlanOptions
from nanoasm.planner.assign import in_slot
from nanoasm.simkeep import SimKeeper, read_sim_state, restore_sim, sim_state_path
from nanoasm.world.scene import Scene, load_scene
from nanoasm.world.sim import SimulatedAFM


@dataclass(frozen=True)
class DriftPoint:
    """One drift estimate beside the truth: time (s), the estimated and the true drift
    since the run's start (nm), and the estimate's covariance (nm², None if it has none)."""

    t: float
    estimate: tuple[float, float]
    truth: tuple[float, float]
    cov: tuple[tuple[float, float], tuple[float, float]] | None

    @property
    def error(self) -> float:
        """Distance between the estimate and the truth, nm."""
        return math.dist(self.estimate, self.truth)

    @property
    def sigma(self) -> float | None:
        """The estimate's σ along its worst direction, nm."""
        return None if self.cov is None else math.sqrt(max(float(np.linalg.eigvalsh(np.asarray(self.cov))[-1]), 0.0))

    @property
    def mahalanobis2(self) -> float | None:
        """Squared Mahalanobis distance of the error under the estimate's covariance."""
        if self.cov is None:
            return None
        e = np.subtract(self.estimate, self.truth)
        return float(e @ np.linalg.solve(np.asarray(self.cov) + 1e-9 * np.eye(2), e))


class _DriftLog:
    """A subscriber keeping the drift estimates sent during a run."""

    def __init__(self):
        self.docs: list[dict] = []

    def __call__(self, topic: str, doc) -> None:
        if topic == "drift":
            self.docs.append(as_dict(doc))

    def against(self, sim: SimulatedAFM, epoch: float) -> tuple[DriftPoint, ...]:
        """The estimates beside the simulated truth (the harness's to read, never the executor's)."""
        o0 = np.asarray(sim.true_offset(epoch))
        out = []
        for d in self.docs:
            truth = np.asarray(sim.true_offset(float(d["t"]))) - o0
            cov = None if d.get("cov") is None else tuple(tuple(float(v) for v in r) for r in d["cov"])
            out.append(DriftPoint(float(d["t"]), tuple(float(v) for v in d["offset"]),
                                  (float(truth[0]), float(truth[1])), cov))
        return tuple(out)


@dataclass(frozen=True)
class PushEnd:
    """One push as the truth saw it: the object (the run's id), how long the push was
    planned (nm, from where it started to where it was to end) and how far from that end
    the object truly came to rest (nm, layout frame)."""

    object: str
    planned: float
    off: float


class _PushLog:
    """A subscriber keeping, after every push, where the pushed objects truly are."""

    def __init__(self, sim: SimulatedAFM):
        self.sim = sim
        self.rows: list[tuple[str, tuple, tuple, tuple]] = []      # ..., every true body (Body) then

    def __call__(self, topic: str, doc) -> None:
        if topic == "push":
            d = as_dict(doc)
            self.rows.append((d["op"]["object"], tuple(d["before"]), tuple(d["op"]["expect"]["at"]),
                              self.sim.truth()))

    def ends(self, sim: SimulatedAFM, summary: RunSummary, ids: dict[str, str]) -> tuple[PushEnd, ...]:
        ox, oy = sim.true_offset(summary.epoch)
        dx, dy = ox - summary.origin[0], oy - summary.origin[1]
        out = []
        where: dict[str, int] = {}                  # the place of each id in truth(), the same each push
        for obj, before, expect, truth in self.rows:
            if not where:
                where = {b.id: k for k, b in enumerate(truth)}
            k = where.get(ids.get(obj, ""))
            if k is not None:
                at = truth[k].at
                out.append(PushEnd(obj, math.dist(before, expect), math.dist((at[0] + dx, at[1] + dy), expect)))
        return tuple(out)


@dataclass(frozen=True)
class Outcome:
    """A dry-run's report plus the figures derived from it, its drift estimates beside
    the simulated truth, and the slots the truth has filled (:func:`truth_slots`, the
    way an outside scorer counts) against the run's own verdict."""

    report: Report
    summary: RunSummary
    filled: tuple[str, ...]
    errors: dict[str, float]          # centre error of every assigned slot, nm
    drift: tuple[DriftPoint, ...] = ()
    truly_filled: tuple[str, ...] = ()
    pushes: tuple[PushEnd, ...] = ()
    ids: dict[str, str] = field(default_factory=dict)     # identified id -> the scene's id
    calibration: Calibration | None = None                # the lever the run compensated with

    @property
    def verdict_filled(self) -> tuple[str, ...]:
        """The slots the run's own check scans call filled."""
        return tuple(v.target for v in self.report.slots if v.state == "filled")

    @property
    def disagreements(self) -> tuple[str, ...]:
        """Slots where the run's verdict and the truth differ (filled or not)."""
        mine, truth = set(self.verdict_filled), set(self.truly_filled)
        return tuple(sorted(mine ^ truth))

    @property
    def rms_error(self) -> float:
        vals = [self.errors[t] for t in self.filled]
        return math.sqrt(sum(v * v for v in vals) / len(vals)) if vals else math.nan


#: The run log's channels of the truth, which this harness alone writes: (topic, schema,
#: what it holds), as :data:`nanoasm.executor.runlog.TOPICS` lists the executor's.
TRUTH_TOPICS = (
    ("/sim/truth", "nanoasm.SimTruth", "dry-runs only, from the harness: true objects before and after, true drift"),
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
               drift: tuple[DriftPoint, ...], t: float) -> None:
    """The true objects (layout frame) before and after the run, and which identified object
    each one is (``ids``: identified id -> scene id); with the final ones, the true drift
    since the run's start at the time of each drift estimate; then the log is finished."""
    true_drift = {"drift": [{"t": p.t, "offset": list(p.truth)} for p in drift]}
    for phase, bodies, extra in (("initial", initial, {}), ("final", final, true_drift)):
        log.write("/sim/truth", {"phase": phase, "objects": [b.to_dict() for b in bodies], "ids": ids, **extra}, t)
    log.write_bodies("/sim/truth/scene", [b.to_dict() for b in final], t, prefix="truth", colour=_TRUTH_COLOUR)
    log.finish()


def _layout_frame(sim: SimulatedAFM, summary: RunSummary, bodies: tuple[Body, ...]) -> tuple[Body, ...]:
    """Truth moved into the layout frame: the scanner frame at the run's start (its
    ``epoch``) less the layout origin the run chose."""
    ox, oy = sim.true_offset(summary.epoch)
    dx, dy = ox - summary.origin[0], oy - summary.origin[1]
    return tuple(plain(b, (b.at[0] + dx, b.at[1] + dy)) for b in bodies)


def row_drift(sim: SimulatedAFM, summary: RunSummary):
    """``at -> (dx, dy)``: the true drift (nm, since the run's start) that the first full
    scan's row through layout position ``at`` carried, from the simulated world's record
    of that scan (none recorded, as in a world restored from a state before it: zero)."""
    if sim.first_scan is None:
        return lambda at: (0.0, 0.0)
    t0, y0, pixel, line, lines = sim.first_scan
    o0 = np.asarray(sim.true_offset(summary.epoch), float)
    oy = float(summary.origin[1])

    def shift(at) -> tuple[float, float]:
        row = min(max((float(at[1]) + oy - y0) / pixel, 0.0), lines - 1.0)
        d = np.asarray(sim.true_offset(t0 + (row + 0.5) * line), float) - o0
        return float(d[0]), float(d[1])

    return shift


def match_ids(found, truth: tuple[Body, ...], reach: float = 500.0, shift=None) -> dict[str, str]:
    """Identified object id -> the scene's id of the true object it is.

    A full scan takes minutes, so the objects it shows are shifted by the drift of the
    time their line was recorded (hundreds of nm, more than the objects' spacing on a
    wide area): ``shift(at)`` gives that drift (:func:`row_drift`), taken out before they
    are matched as a whole, by ``linear_sum_assignment`` over kind, size and distance,
    pairs farther than ``reach`` left out. Objects that identification invented keep
    their own ids.
    """
    found = list(found)
    if not found or not truth:
        return {}
    cost = np.full((len(found), len(truth)), 1e9)
    for i, o in enumerate(found):
        dx, dy = (0.0, 0.0) if shift is None else shift(o.at)
        for j, b in enumerate(truth):
            d = math.dist((o.at[0] - dx, o.at[1] - dy), b.at)
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


def truth_slots(layout: Layout, final) -> tuple[str, ...]:
    """The slots that true objects fill, as an outside scorer counts them: the largest
    matching of slots to distinct objects of their kind and size within the layout's
    tolerance (position, and a rod's angle), whatever the run assigned."""
    targets, final = list(layout.targets), list(final)
    if not targets or not final:
        return ()
    ok = np.array([[in_slot(t, o, layout.tolerance) for o in final] for t in targets], dtype=bool)
    rows, cols = linear_sum_assignment(-ok.astype(float))
    return tuple(sorted(targets[i].id for i, j in zip(rows, cols) if ok[i, j]))


def exec_options(scene: Scene, strategy: str = "full", contact_batch: int | None = None) -> ExecOptions:
    """The executor's options in a dry-run of ``scene``: it pushes at the scene's
    ``[timing] push_speed`` (the simulated instrument's); ``contact_batch`` (None: the
    default) as ``nanoasm dry-run --contact-batch`` gives it."""
    return ExecOptions(strategy=strategy, push_speed=scene.params.timing.push_speed).batched(contact_batch)


def dry_run(scene: Scene, layout: Layout, *, seed: int | None = None,
            options: ExecOptions | None = None, plan_options: PlanOptions | None = None,
            subscribers: list[Subscriber] | None = None, scene_name: str | None = None,
            layout_name: str | None = None, keep_sim: str | os.PathLike | None = None,
            resume: tuple[dict, dict] | None = None, reviewed: ReviewedPlan | None = None,
            scan: ScanArea | None = None) -> Outcome:
    """Run the assembly of ``layout`` on a simulated AFM holding ``scene``.

    ``keep_sim``: keep the simulated world at every checkpoint in this file (for
    resuming; see :mod:`nanoasm.simkeep`). ``resume``: ``(checkpoint state, kept world)``
    of a stopped dry-run to go on with instead of starting afresh; the report's wall time
    then counts the stopped run's up to the checkpoint (its compute by stage) too. Run
    logs among the ``subscribers`` get the scene and the truth from this harness.
    ``reviewed``, ``scan``: the plan to start from and the full scan, as :func:`nanoasm.run.run`.
    """
    seed = scene.seed if seed is None else seed
    seed = 0 if seed is None else seed
    t_wall = time.perf_counter()
    wall_before = 0.0               # the stopped run's compute up to its checkpoint, s
    if resume is not None:          # the world as the stopped run left it
        state, kept = resume
        sim, start_clock, initial_sample = kept["sim"], kept["start_clock"], kept["initial"]
        wall_before = sum(float(v) for v in state["wall"].values())
    else:
        sim = SimulatedAFM(scene, seed=seed)
        start_clock = sim.clock()
        initial_sample = sim.truth()
    # the executor compensates with the lever calibrated through the simulated instrument,
    # never with the truth's constants (nanoasm.calibrate); its maps cover the working area
    side = min(max(*layout.area, *scene.area), *sim.config.xy_range)
    try:
        cal = simulated_calibration(sim, seed, side)
        lever = {"lever": cal.lever(scene.params.cantilever.signal_limit), "baselines": cal.baselines}
    except CalibrationFailed as exc:        # as a lab would: the nominal lever, said so
        cal, lever = None, {}
        warn([f"the simulated lever's calibration failed ({exc}): compensating with the dissertation's "
              f"nominal lever"])
    options = options or exec_options(scene)
    if cal is not None:             # the tip's own friction on the substrate, as calibrated
        options = replace(options, substrate_friction=max(cal.values["mu_ts"].value, 0.0))
    assembly = Assembly(layout, options, plan_options, source=layout_name, reviewed=reviewed, scan=scan, **lever)
    drift_log, push_log = _DriftLog(), _PushLog(sim)
    subscribers = [*(subscribers or ()), drift_log, push_log]
    if keep_sim is not None:
        keeper = SimKeeper(keep_sim, sim, start_clock, initial_sample)
        subscribers.append(keeper)
        if resume is not None:      # the resumed log starts at the checkpoint it goes on from: so does its world
            keeper.keep(float(resume[0]["t"]))
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
    ids = match_ids(summary.env.objects, initial, shift=row_drift(sim, summary))
    drift = drift_log.against(sim, summary.epoch)
    for log in logs:
        _log_truth(log, initial, final, ids, drift, sim.clock())
    initial, final = own_frame(summary, initial), own_frame(summary, final)    # a layout registered by its marks
    wall = wall_before + time.perf_counter() - t_wall
    report = report_of(summary, layout, total, wall, layout_name=layout_name,
                       scene_name=scene_name, seed=seed, objects=(initial, final), ids=ids,
                       plan=None if reviewed is None else reviewed.source)
    filled, errors = filled_slots(layout, report.assignment, {b.id: b for b in final})
    return Outcome(report, summary, filled, errors, drift,
                   truth_slots(layout, final), push_log.ends(sim, summary, ids), ids, cal)



def dry_run_files(scene_file: Path, layout_file: Path, *, seed: int | None = None, strategy: str = "full",
                  plan_options: PlanOptions | None = None, log: LogTo = LogTo(), report: Path | None = None,
                  progress: AbstractContextManager | None = None, plan: Path | None = None, region=None,
                  pixels: int | None = None, contact_batch: int | None = None) -> tuple[Outcome, Layout]:
    """A dry-run as ``nanoasm dry-run`` makes it: the scene and layout files, the run log
    (with the simulated world kept beside it, for resuming), the report file.
    ``progress`` gives extra subscribers for the run (a progress line) while it runs;
    ``plan``, ``region``, ``pixels``: the reviewed plan to execute and the full scan
    (:func:`nanoasm.harness.run_start`); ``contact_batch``: ``ExecOptions.contact_batch``
    (None: its default). Returns the outcome and the layout."""
    scene = load_scene(scene_file)
    layout = load_layout(layout_file)
    options = exec_options(scene, strategy, contact_batch)
    reviewed, scan, start = run_start(layout, layout_file, scene.params.scanner, options.pixel_size, plan=plan,
                                      region=region, pixels=pixels, align=(plan_options or PlanOptions()).align)
    meta = {"kind": "dry-run", "strategy": strategy, "seed": seed, "scene": str(scene_file),
            "layout": str(layout_file), **start}
    outcome = _logged(scene, layout, meta, log, report, progress, seed=seed, reviewed=reviewed, scan=scan,
                      options=options, plan_options=plan_options,
                      scene_name=str(scene_file), layout_name=str(layout_file),
                      keep_sim=None if log.path is None else sim_state_path(log.path))
    return outcome, layout


def resume_dry_run(stopped: Path, *, plan_options: PlanOptions | None = None, log: LogTo = LogTo(),
                   report: Path | None = None,
                   progress: AbstractContextManager | None = None) -> tuple[Outcome, Layout]:
    """Go on with the dry-run logged in ``stopped`` from the checkpoint where its kept
    world stands, with the scene, layout, strategy and seed of its log; logged to
    ``log.path`` or else a new log beside the old one. Returns the outcome and the layout."""
    if not stopped.is_file():
        raise InputError(str(stopped), None, "no such run log")
    kept = read_sim_state(sim_state_path(stopped))      # JSON, its outer fields checked
    point = resume_point(stopped, "dry-run", at=kept["t"])
    meta = point.metadata
    if point.scene is None:
        raise InputError(str(stopped), "scene.json", "the log has no scene attached")
    # of the log's scene, and of the checkpoint (unless that was lost: then the world is ahead of it)
    kept = restore_sim(sim_state_path(stopped), kept, point.scene, None if point.behind else point.state)
    warn(point.warnings)
    seed = int(meta["seed"]) if meta.get("seed", "None") not in ("None", "") else None
    log = replace(log, path=log.path or resumed_log_path(stopped))
    given = {k: meta[k] for k in ("kind", "strategy", "seed", "scene", "layout") if k in meta}
    outcome = _logged(point.scene, point.layout, {**given, "resumed_from": str(stopped)}, log, report, progress,
                      seed=seed, options=exec_options(point.scene, point.state["strategy"],
                                                      checkpoint_batch(point.state)),
                      plan_options=replace(plan_options or PlanOptions(), seed=seed or 0),
                      scene_name=meta.get("scene"), layout_name=meta.get("layout"),
                      keep_sim=sim_state_path(log.path), resume=(point.state, kept), carry=point.inherited)
    return outcome, point.layout


def _logged(scene: Scene, layout: Layout, meta: dict, log: LogTo, report: Path | None,
            progress: AbstractContextManager | None, carry=None, **kwargs) -> Outcome:
    """:func:`dry_run` with its run log (carrying over ``carry``, a resumed run's
    :class:`~nanoasm.executor.resume.Inherited`), progress subscribers and report file."""
    with run_logs(log, layout, meta, truth=True, carry=carry) as logs, progress or nullcontext([]) as shown:
        if kwargs.get("keep_sim") is not None:
            # a log written over (--force): the world kept for the old one must not stay beside it
            Path(kwargs["keep_sim"]).unlink(missing_ok=True)
        outcome = dry_run(scene, layout, subscribers=[*shown, *logs], **kwargs)
    if report is not None:
        outcome.report.save(report)
    return outcome
