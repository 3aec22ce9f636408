"""Runs: the executor against a real instrument, and the report of what it did.

The twin of :mod:`nanoasm.dryrun`. :func:`run` puts the executor in front of an open
instrument (any :class:`~nanoasm.instrument.Instrument`) and reports what the run
believes it did: a real run has no truth to compare with. :func:`run_files` is the
command line's: the hardware backend an instrument file names (NI-DAQmx or Nanonis,
:func:`open_hardware`), the run log, resuming a
stopped run from its log, the report file. Both harnesses report through
:func:`nanoasm.harness.report_of`.
"""

from __future__ import annotations

from contextlib import AbstractContextManager, nullcontext
from dataclasses import replace
from pathlib import Path

from nanoasm.cad.layout import Layout, load_layout
from nanoasm.errors import InputError
from nanoasm.executor.assembly import Assembly
from nanoasm.executor.checkpoints import checkpoint_batch
from nanoasm.executor.engine import RunEngine, Subscriber
from nanoasm.executor.lever_file import InstrumentLever
from nanoasm.executor.report import Report
from nanoasm.executor.resume import ResumePoint, ShiftedClock, clock_shift, resume_point, resumed_log_path
from nanoasm.executor.strategy import ExecOptions
from nanoasm.executor.reviewed_plan import ReviewedPlan
from nanoasm.executor.scan_area import ScanArea
from nanoasm.harness import LogTo, report_of, run_logs, run_start, warn
from nanoasm.planner import PlanOptions


def run(layout: Layout, instrument, *, options: ExecOptions | None = None,
        plan_options: PlanOptions | None = None, subscribers: list[Subscriber] | None = None,
        layout_name: str | None = None, resume: ResumePoint | None = None, lever: InstrumentLever | None = None,
        reviewed: ReviewedPlan | None = None, scan: ScanArea | None = None) -> Report:
    """Assemble ``layout`` on ``instrument`` (open; parked whatever happens), compensating
    with ``lever`` (the instrument file's; None: the seed's lever, for tests), starting
    from the ``reviewed`` plan (None: a plan of its own) after a full scan of ``scan``
    (None: the layout's area centred in the scanner's range).

    ``resume``: a stopped run's last checkpoint
    (:func:`~nanoasm.executor.resume.resume_point`) to go on from; the instrument's clock
    then goes on from the stopped run's. The report's instrument time is this run's own.
    """
    assembly = Assembly(layout, options, plan_options, source=layout_name, reviewed=reviewed, scan=scan,
                        **({} if lever is None else {"lever": lever.lever, "baselines": lever.baselines}))
    inst = instrument
    if resume is not None:          # the clock goes on from the stopped run's
        inst = ShiftedClock(instrument, clock_shift(resume.state, instrument.clock()))
    t0 = inst.clock()
    procedure = (assembly.resume(inst.config, resume.state) if resume is not None
                 else assembly.procedure(inst.config))
    summary = RunEngine(inst, list(subscribers or ())).run(procedure)
    total = inst.clock() - t0
    return report_of(summary, layout, total, sum(summary.wall.values()), layout_name=layout_name,
                     plan=None if reviewed is None else reviewed.source)


def run_files(instrument_file: Path, layout_file: Path | None = None, *, strategy: str = "full",
              resume_from: Path | None = None, log: LogTo = LogTo(), report: Path | None = None,
              progress: AbstractContextManager | None = None, plan_options: PlanOptions | None = None,
              plan: Path | None = None, region=None, pixels: int | None = None,
              contact_batch: int | None = None) -> Report:
    """A run as ``nanoasm run`` makes it: the hardware backend of ``instrument_file``,
    the layout file or, with ``resume_from``, the layout, strategy and last checkpoint of
    that stopped run's log (logged to ``log.path`` or else a new log beside it), the run
    log with the instrument file attached, the report file. ``progress`` gives extra
    subscribers for the run (a progress line) while it runs; ``plan_options``: how to plan
    (and register a layout with marks: ``align``); ``plan``, ``region``, ``pixels``: the
    reviewed plan to execute and the full scan (:func:`nanoasm.harness.run_start`);
    ``contact_batch``: ``ExecOptions.contact_batch`` (None: its default; a resumed run
    takes its checkpoint's)."""
    from nanoasm.executor.instrument_file import load_instrument_config

    point = None
    if resume_from is not None:
        point = resume_point(resume_from, "run")
        warn(point.warnings)
        layout, strategy = point.layout, point.state["strategy"]
        contact_batch = checkpoint_batch(point.state)
        layout_file = Path(point.metadata.get("layout", "layout.json"))
        log = replace(log, path=log.path or resumed_log_path(resume_from))
    else:
        layout = load_layout(layout_file)
    config = load_instrument_config(instrument_file)
    mu_ts = None if config.lever is None else config.lever.mu_ts
    options = ExecOptions(strategy=strategy, substrate_friction=mu_ts or 0.0).batched(contact_batch)
    reviewed, scan, start = run_start(layout, layout_file, config.scanner, options.pixel_size, plan=plan,
                                      region=region, pixels=pixels, align=(plan_options or PlanOptions()).align)
    if config.lever is None:        # the seed's lever would mis-aim every push on another lever
        raise InputError(str(instrument_file), "cantilever", "missing table: a run compensates the tip's deflection "
                         "with the lever's constants; measure them with 'nanoasm calibrate --instrument "
                         f"{instrument_file} -o cal.toml' and paste its tables into the file")
    meta = {"kind": "run", "strategy": strategy, "layout": str(layout_file), "instrument": str(instrument_file),
            **start}
    if resume_from is not None:
        meta["resumed_from"] = str(resume_from)
    suffix = instrument_file.suffix.lower()
    attach = {"instrument" + suffix: ("application/" + suffix.lstrip("."), instrument_file.read_bytes())}
    carry = None if point is None else point.inherited
    with (open_hardware(config) as hardware, run_logs(log, layout, meta, attachments=attach, carry=carry) as logs,
          progress or nullcontext([]) as shown):
        rep = run(layout, hardware, options=options, subscribers=[*shown, *logs], layout_name=str(layout_file),
                  resume=point, plan_options=plan_options, lever=config.lever, reviewed=reviewed, scan=scan)
    if report is not None:
        rep.save(report)
    return rep


def open_hardware(config):
    """The open instrument of the backend a loaded instrument file names (``backend``):
    :class:`~nanoasm.executor.nidaq.NiDaqInstrument` or
    :class:`~nanoasm.executor.nanonis.NanonisInstrument`; a context manager that parks."""
    if config.backend == "nanonis":
        from nanoasm.executor.nanonis import NanonisInstrument

        return NanonisInstrument(config)
    from nanoasm.executor.nidaq import NiDaqInstrument

    return NiDaqInstrument(config)
