"""What the two harnesses share: the run log they write and the one way they make a report.

A harness puts the executor (an :class:`~nanoasm.executor.assembly.Assembly` on a
:class:`~nanoasm.executor.engine.RunEngine`) in front of an instrument and reports what
happened: :mod:`nanoasm.run` in front of a real one, :mod:`nanoasm.dryrun` in front of
the simulated AFM, whose truth it alone reads.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

from nanoasm.bodies import Body
from nanoasm.cad.layout import Layout
from nanoasm.errors import InputError
from nanoasm.executor.documents import STOP, StopDoc
from nanoasm.executor.engine import RunState
from nanoasm.executor.ledger import ACTIVITIES
from nanoasm.executor.report import InstrumentTime, Report, WallTime
from nanoasm.executor.reviewed_plan import ReviewedPlan, load_reviewed
from nanoasm.executor.runlog import RunLog
from nanoasm.executor.scan_area import ScanArea, scan_area
from nanoasm.executor.summary import RunSummary
from nanoasm.planner.plan import Assignment


@dataclass(frozen=True)
class LogTo:
    """Where a run is logged: an MCAP file (``path``), a live stream on 127.0.0.1 at
    ``port`` (``live``), both or neither."""

    path: Path | None = None
    live: bool = False
    port: int = 8765


@contextmanager
def run_logs(to: LogTo, layout: Layout, metadata: dict, carry=None, **options) -> Iterator[list[RunLog]]:
    """The run log and live stream as a list of engine subscribers (empty when ``to`` asks
    for neither); closed on the way out, whatever happens. ``carry``: a resumed run's
    :class:`~nanoasm.executor.resume.Inherited`, written first (:meth:`RunLog.carry`);
    ``options`` go to the RunLog."""
    if to.path is None and not to.live:
        yield []
        return
    from nanoasm.executor.runlog import command_line, open_run_log

    log = open_run_log(to.path, live_port=to.port if to.live else None, layout=layout,
                       metadata={**metadata, "command": command_line()}, **options)
    if log.server is not None:
        print(f"live: ws://127.0.0.1:{log.port} (Foxglove: Open connection > Foxglove WebSocket)", file=sys.stderr)
    try:
        if carry is not None:
            log.carry(carry)
        yield [log]
    except BaseException as exc:
        reason = _signal_stop(exc)
        if reason is not None and not log.stopped:      # stopped before its run began (calibration, planning)
            log(STOP, StopDoc(RunState.ABORTED.value, reason))
        raise
    finally:
        log.close()
        if to.path is not None:
            print(f"{to.path}: written", file=sys.stderr)


def _signal_stop(exc: BaseException) -> str | None:
    """The reason a stop by Ctrl-C or SIGTERM gives (the engine's words), else None."""
    if isinstance(exc, KeyboardInterrupt):
        return "interrupted (Ctrl-C)"
    reason = getattr(type(exc), "stop_reason", None)
    return reason if isinstance(reason, str) else None


def warn(lines) -> None:
    """Warnings a harness gives before it runs (a damaged log it resumes), one line each
    on stderr."""
    for line in lines:
        print(f"nanoasm: warning: {line}", file=sys.stderr)


def plain(o: Body, at: tuple[float, float] | None = None) -> Body:
    """``o`` (an identified or simulated object) as the report holds it: a Body, a rod's
    angle in [0, 180), moved to ``at`` when given."""
    return Body(o.id, o.kind, o.at if at is None else at, o.diameter,
                None if o.angle is None else o.angle % 180.0, o.length)


def report_of(summary: RunSummary, layout: Layout, instrument_total: float, wall_total: float, *,
              layout_name: str | None = None, scene_name: str | None = None, seed: int | None = None,
              objects: tuple[tuple[Body, ...], tuple[Body, ...]] | None = None,
              ids: dict[str, str] | None = None, plan: str | None = None) -> Report:
    """The report of a run from its summary: the one constructor of both harnesses.

    A run reports the objects it identified and those it believes in at the end (in the
    layout's own frame when the run registered it by its marks). A
    dry-run gives what its truth tells instead: the true objects before and after
    (``objects``, the layout's own frame) and which true object each identified one is (``ids``:
    identified id -> scene id), by which the assignment and the pushes are reported.
    ``instrument_total`` and ``wall_total`` are the run's seconds on the instrument and
    of this program; ``plan``: the reviewed plan file the run executed, if any.
    """
    ids = ids or {}
    if objects is None:
        belief = summary.belief
        objects = (tuple(plain(o) for o in summary.env.objects),
                   tuple(plain(o) for oid, o in belief.objects.items() if oid not in belief.lost))
        objects = (own_frame(summary, objects[0]), own_frame(summary, objects[1]))
    t, w = dict(summary.times), summary.wall
    # the engine lifts and parks the tip after the procedure's last step: lifted travel
    t["travel"] += max(instrument_total - sum(t.get(a, 0.0) for a in ACTIVITIES), 0.0)
    return Report(
        scene=scene_name, layout=layout_name, seed=seed, targets=layout.targets,
        initial_objects=objects[0], final_objects=objects[1],
        assignment=tuple(Assignment(a.target, ids.get(a.object, a.object)) for a in summary.assignment),
        pushed=tuple(ids.get(p, p) for p in summary.pushed), unfilled=summary.unfilled, counts=summary.counts,
        instrument_time=InstrumentTime(t["full_scan"], t["local_scan"], t["push"], t["travel"], instrument_total,
                                       t.get("mode_switch", 0.0)),
        wall_time=WallTime(w["identify"], w["plan"], w["execute"], wall_total),
        slots=tuple(replace(v, object=None if v.object is None else ids.get(v.object, v.object))
                    for v in summary.slots),
        registration=summary.registration, plan=plan,
    )


def own_frame(summary: RunSummary, bodies: tuple[Body, ...]) -> tuple[Body, ...]:
    """``bodies`` (the run's frame, the scan's) in the layout's own frame: moved back by
    the registration of its marks, when the run made one."""
    if summary.registration is None:
        return bodies
    back = summary.registration.inverse()
    return tuple(plain(back.body(b)) for b in bodies)


def run_start(layout: Layout, layout_file, config, pixel_size: float, *, plan=None, region=None,
              pixels: int | None = None, align: str = "rigid") -> tuple[ReviewedPlan | None, ScanArea | None, dict]:
    """How a run of ``layout`` (file ``layout_file``) on a scanner of ``config`` (an
    InstrumentConfig) starts, checked before anything moves: the reviewed ``plan`` file it
    executes (:func:`~nanoasm.executor.reviewed_plan.load_reviewed`; None: it plans), the
    full scan ``region`` and ``pixels`` ask for (:func:`~nanoasm.executor.scan_area.scan_area`,
    at ``pixel_size`` by default; None: the layout's area centred in the range, which must
    fit it: :func:`check_fits`), and the run log's metadata saying so."""
    if region is None:
        check_fits(layout, str(layout_file), config)
    scan = scan_area(region, pixels, layout, config.xy_range, pixel_size)
    reviewed = None if plan is None else load_reviewed(plan, layout, str(layout_file), align)
    meta = {} if plan is None else {"plan": str(plan)}
    if scan is not None:
        meta["full_scan"] = f"region {' '.join(f'{v:g}' for v in scan.region)} nm, {scan.pixels} pixels a side"
    return reviewed, scan, meta


def check_fits(layout: Layout, source: str | None, config) -> None:
    """Refuse, before a run starts, a layout whose working area does not fit the XY range
    of the scanner (``config``, an InstrumentConfig): the run scans it centred in the
    range. One line naming the layout file (``source``) and ``area``."""
    (w, h), (xr, yr) = layout.area, config.xy_range
    side = max(w, h)            # the full scan is the square on the area's longer side
    if side > xr or side > yr:
        raise InputError(source, "area", f"a full scan of {side:g} x {side:g} nm does not fit the scanner's XY "
                                         f"range {xr:g} x {yr:g} nm")
