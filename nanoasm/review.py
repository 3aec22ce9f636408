"""``nanoasm review run.mcap``: what a logged dry-run or run did, as a table and a plot.

Everything comes from the log (:func:`nanoasm.executor.logread.read_log`): the layout
attachment, the plan, the pushes, checkpoints and the executor's belief, the drift
estimate, and in a dry-run the simulated truth the harness added (``/sim/truth``). A slot's
error is measured against that truth when the log has it, else against the executor's
last belief. Objects are named by the run's ids everywhere (those of its events and
pushes); a true body carries the scene's id, shown only as the truth (``/sim/truth``'s
``ids`` tell which identified object each is). A log cut short (a killed process) is
reviewed as far as it goes. The plot is :mod:`nanoasm.review_plot`'s.
"""

from __future__ import annotations

import math
import os
import struct
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from nanoasm.bodies import Body
from nanoasm.errors import InputError
from nanoasm.executor.documents import (CHANNELS, CHECKPOINT, DRIFT, ENVIRONMENT, PLAN, PUSH,
                                        RESULT, STOP, CheckpointDoc, DocumentError, DriftDoc, PushDoc, StopDoc,
                                        body_from_stored)
from nanoasm.executor.ledger import ACTIVITIES
from nanoasm.listing import LISTED, first
from nanoasm.schema import Table

#: The dry-run harness's channel of the simulated truth (:mod:`nanoasm.dryrun`).
TRUTH = "/sim/truth"


@dataclass(frozen=True)
class SlotRow:
    """An assigned slot: the object the run put there (the run's id), its centre error
    against the pose it is measured on (``pose``: the true body, or the last belief), and
    the scene's id of that true body (``truth``, None without simulated truth)."""

    target: str
    object: str | None
    error: float | None        # centre error, nm (None: no pose known)
    filled: bool
    truth: str | None = None
    pose: Body | None = None


@dataclass
class Review:
    """A run log's figures."""

    path: str
    complete: bool
    problem: str | None
    kind: str                                  # "dry-run" or "run"
    metadata: dict[str, str]
    end_time: float | None
    stop: StopDoc | None = None
    layout: Any = None
    source: str = "belief"                     # what slot errors are measured against
    slots: list[SlotRow] = field(default_factory=list)
    verdict: list = field(default_factory=list)     # the run's own check scans (SlotVerdict)
    unfilled: list[tuple[str, str]] = field(default_factory=list)
    pushes: int = 0
    failed_pushes: int = 0
    failures: list[tuple[str, str]] = field(default_factory=list)   # (object, cause)
    times: dict[str, float] = field(default_factory=dict)
    total_time: float | None = None
    drift: list[tuple[float, float, float, float, float]] = field(default_factory=list)  # t dx dy sx sy
    initial: list[Body] = field(default_factory=list)     # identified objects
    final: list[Body] = field(default_factory=list)       # last belief
    truth_initial: list[Body] = field(default_factory=list)   # true bodies, with the scene's ids
    truth_final: list[Body] = field(default_factory=list)
    truth_ids: dict[str, str] = field(default_factory=dict)   # the run's id -> the scene's id of that body
    true_drift: list[tuple[float, float, float]] = field(default_factory=list)   # t dx dy (the truth's)
    scan: Any = None                                      # the first full scan (a HeightImage), if logged
    paths: list[tuple[list, str]] = field(default_factory=list)   # (tip path, verdict)
    notes: list[str] = field(default_factory=list)        # messages skipped, and why
    damage: list[str] = field(default_factory=list)       # parts of the file skipped, and what is lost
    cut: str | None = None                                # why the log ends before its footer

    @property
    def filled(self) -> int:
        return sum(s.filled for s in self.slots)

    def last_drift_error(self) -> float | None:
        """How far the last drift estimate is from the true drift at its time, nm (None:
        no truth logged for it)."""
        if not self.drift or not self.true_drift or abs(self.drift[-1][0] - self.true_drift[-1][0]) > 1e-6:
            return None
        return math.dist(self.drift[-1][1:3], self.true_drift[-1][1:3])


def _check_started(log) -> None:
    """Refuse a file whose run never started in it. Every run log begins with the MCAP
    header of profile ``nanoasm.runlog/1`` and then the ``nanoasm`` metadata record (of
    that format), both flushed before the run does anything: a file with neither (random
    bytes after the MCAP magic, junk records, another tool's MCAP) is no run log however
    much of it reads. A log cut before its metadata record is still one when all of its
    first record that is there is such a header."""
    from nanoasm.executor.runlog import FORMAT

    meta = log.metadata.get("nanoasm")
    if meta is not None and meta.get("format") == FORMAT:
        return
    if meta is None and not log.complete and _starts_as_run_log(log.path, FORMAT):
        return
    why = ("no 'nanoasm' metadata record" if meta is None
           else f"its 'nanoasm' metadata record is not of format {FORMAT!r}")
    raise InputError(log.path, None, f"not a readable nanoasm run log ({why}{'; ' + log.cut if log.cut else ''})")


def _starts_as_run_log(path: str, profile: str) -> bool:
    """Whether the file's first bytes, as far as they go, are the MCAP magic and a header
    record (opcode 1, any length) of ``profile``."""
    name = profile.encode("utf-8")
    expected = [*b"\x89MCAP0\r\n\x01", *[None] * 8, *struct.pack("<I", len(name)), *name]
    with open(path, "rb") as fh:
        head = fh.read(len(expected))
    return all(want is None or got == want for got, want in zip(head, expected))


def review(path: str | os.PathLike) -> Review:
    """Read and summarise a run log; raises InputError for a file that is no run log.
    Messages that are not what their channel holds are skipped, each with a note."""
    from nanoasm.cad.layout import layout_from_dict
    from nanoasm.executor.logread import read_log

    log = read_log(path)
    meta = dict(log.metadata.get("nanoasm", {}))
    kind = "dry-run" if "dry-run" in log.metadata or log.topic(TRUTH) else meta.get("kind", "run")
    rev = Review(str(path), log.complete, log.problem, kind, meta, log.end_time, cut=log.cut,
                 damage=[d.line() for d in log.damage])
    _check_started(log)
    layout_doc = log.attachment_json("layout.json")
    if layout_doc is not None:
        try:
            rev.layout = layout_from_dict(layout_doc, "layout.json")
        except (InputError, ValueError, TypeError) as err:
            rev.notes.append(f"layout.json skipped: {err}")
    docs = log.documents(ENVIRONMENT, PLAN, PUSH, CHECKPOINT, DRIFT, RESULT, STOP, notes=rev.notes)
    last = {topic: doc for topic, doc in docs}
    reg = next((doc.registration for topic, doc in docs if topic == PLAN and doc.registration is not None), None)
    if rev.layout is not None and reg is not None:      # registered by its marks: the log is in the scan's frame
        rev.layout = rev.layout.mapped(reg, rev.layout.area)
    rev.stop = last.get(STOP)
    envs = [doc for topic, doc in docs if topic == ENVIRONMENT]
    rev.initial = list(envs[-1].objects) if envs else []
    pushes: list[PushDoc] = [doc for topic, doc in docs if topic == PUSH]
    rev.paths = [(list(p.op.tip_path), p.verdict) for p in pushes]
    ledger, lost = _replay(rev, docs)

    # what the run did: its result when it got that far, else the last checkpoint
    res, plan = last.get(RESULT), last.get(PLAN)
    source = res if res is not None else plan
    assignment = [(a.target, a.object) for a in source.assignment] if source is not None else []
    rev.unfilled = [(u.target, u.reason) for u in source.unfilled] if source is not None else []
    counts = res.counts if res is not None else ledger.counts if ledger is not None else {}
    failed = [p for p in pushes if p.failed]
    rev.pushes = int(counts.get("pushes", len(rev.paths)))
    rev.failed_pushes = int(counts.get("failed_pushes", len(failed)))
    if res is not None:
        rev.failures = list(res.failures)
        rev.verdict = list(res.slots)
    else:
        rev.failures = [(str(o), "lost") for o in sorted(lost)]
        rev.failures += [(p.op.object, p.verdict) for p in failed]
    times = res.times if res is not None else ledger.times if ledger is not None else {}
    rev.times = {a: float(times.get(a, 0.0)) for a in ACTIVITIES}
    starts = [m.t for m in log.topic("/events")]
    if res is not None:
        starts.append(res.epoch)
    if starts and rev.end_time is not None:
        rev.total_time = rev.end_time - min(starts)
        if res is not None:         # the lift and park after the last step, as the report counts them
            rev.times["travel"] += max(rev.total_time - sum(rev.times.values()), 0.0)

    # slots: against the simulated truth when the harness logged it, else the last belief;
    # named by the run's ids either way (a true body by the identified object it is)
    truth = _truth(log, rev.notes)
    final = {b.id: b for b in rev.final}
    if "initial" in truth:
        rev.truth_initial = truth["initial"][0]
    if "final" in truth:
        rev.truth_final, rev.truth_ids, rev.true_drift = truth["final"]
        scene = {b.id: b for b in rev.truth_final}
        final = {run: scene[sid] for run, sid in rev.truth_ids.items() if sid in scene}
        rev.source = "simulated truth"
    if rev.layout is not None:
        rev.slots = _slots(rev.layout, assignment, final, rev.truth_ids)
    rev.scan = _scan(log, rev.notes)
    return rev


def _replay(rev: Review, docs: list[tuple[str, Any]]):
    """The executor's belief, replayed: the identified objects, then pushes and checkpoints
    (``rev.final``), and the drift estimates (``rev.drift``). Returns the last checkpoint's
    ledger (None: no checkpoint) and the objects lost by then."""
    belief = {b.id: b for b in rev.initial}
    lost: set[str] = set()
    ledger = None
    for topic, doc in docs:
        if topic == PUSH:
            belief[doc.belief.id] = doc.belief
        elif topic == CHECKPOINT:
            read = _checkpoint(doc, rev.notes)
            if read is not None:
                b, ledger = read
                belief = dict(b.objects) or belief
                lost = set(b.lost)
        elif topic == DRIFT:
            rev.drift.append(_drift_row(doc))
    rev.final = [b for oid, b in belief.items() if oid not in lost]
    return ledger, lost


def _checkpoint(doc: CheckpointDoc, notes: list[str]):
    """A checkpoint's belief and ledger, or None (with a note) when its state lacks them."""
    try:
        return doc.belief(), doc.ledger()
    except DocumentError as err:
        notes.append(f"{CHANNELS[CHECKPOINT]} at t = {doc.t:.3f} s skipped: {err}")
        return None


def _drift_row(doc: DriftDoc) -> tuple[float, float, float, float, float]:
    """(t, dx, dy, sx, sy): the offset and its standard deviations (NaN: no covariance)."""
    dx, dy = doc.offset
    sx, sy = ((math.sqrt(max(doc.cov[0][0], 0.0)), math.sqrt(max(doc.cov[1][1], 0.0))) if doc.cov is not None
              else (math.nan, math.nan))
    return doc.t, dx, dy, sx, sy


def _truth(log, notes: list[str]) -> dict[str, tuple[list[Body], dict[str, str], list[tuple[float, float, float]]]]:
    """The harness's simulated truth by phase: the true bodies, which identified object
    each one is (identified id -> scene id), and the true drift since the run's start at
    each drift estimate's time (``(t, dx, dy)``; logged with the final bodies)."""
    out = {}
    for m in log.topic(TRUTH):
        try:
            t = Table(m.data, "truth document")
            ids = t.table("ids", optional=True)
            drift = [(dt.number("t"), *dt.pair("offset")) for dt in t.tables("drift")]
            out[t.string("phase")] = ([body_from_stored(bt) for bt in t.tables("objects")],
                                      {} if ids is None else {k: ids.string(k) for k in ids.data}, drift)
        except (InputError, ValueError) as err:
            notes.append(f"{TRUTH} at t = {m.t:.3f} s skipped: {err}")
    return out


def _slots(layout, assignment: list[tuple[str, str]], final: dict[str, Body],
           truth_ids: dict[str, str]) -> list[SlotRow]:
    """The assigned slots; ``final``: the pose each of the run's objects is measured on."""
    from nanoasm.dryrun import filled_slots
    from nanoasm.planner.plan import Assignment

    known = {t.id for t in layout.targets}
    pairs = [Assignment(t, o) for t, o in assignment if t in known]
    filled, errors = filled_slots(layout, pairs, final)
    return [SlotRow(a.target, a.object, errors.get(a.target), a.target in filled, truth_ids.get(a.object),
                    final.get(a.object)) for a in pairs]


def _scan(log, notes: list[str]):
    """The first full scan from its attachment (None when the log has none)."""
    from nanoasm.executor.scan_attachment import FULL_SCAN_ATTACHMENT, full_scan_image

    data = log.attachments.get(FULL_SCAN_ATTACHMENT)
    if data is None:
        return None
    try:
        return full_scan_image(data)
    except ValueError as err:
        notes.append(f"{FULL_SCAN_ATTACHMENT} skipped: {err}")
        return None


# -- the table ---------------------------------------------------------------------------

def _minutes(s: float | None) -> str:
    return "-" if s is None else f"{s / 60:.1f} min"


def print_review(rev: Review, console=None) -> None:
    """The review as a rich table (on stdout by default)."""
    from rich.console import Console
    from rich.table import Table as RichTable

    console = console or Console()
    name = (rev.layout.name if rev.layout is not None else None) or "layout"
    n = len(rev.layout.targets) if rev.layout is not None else 0
    title = f"{rev.kind} of {name}: {rev.filled} of {n} slot(s) filled"
    table = RichTable(title=title, show_header=False)
    for line in rev.damage:
        table.add_row("[bold red]damaged[/]", line)
    if rev.cut is not None or (not rev.complete and not rev.damage):
        table.add_row("[bold red]incomplete[/]", _incomplete(rev))
    elif rev.stop is not None and rev.stop.state != "done":
        table.add_row("[bold red]stopped[/]", f"{rev.stop.state}: {rev.stop.reason}")
    for note in rev.notes:
        table.add_row("[bold red]skipped[/]", note)
    for k in ("strategy", "seed", "command", "resumed_from"):
        if rev.metadata.get(k):
            table.add_row(k.replace("_", " "), rev.metadata[k])
    mine = {v.target: v for v in rev.verdict}
    if rev.verdict:
        states = Counter(v.state for v in rev.verdict)
        table.add_row("the run's verdict", ", ".join(f"{states.get(k, 0)} {k}" for k in ("filled", "missed",
                                                                                        "unfilled"))
                      + " (its check scans of every slot)")
    slots, more = first(rev.slots)
    for s in slots:
        err = "no pose" if s.error is None else f"{s.error:.1f} nm"
        truth = "" if s.truth is None else f" (truth: scene id {s.truth})"
        row = f"{'filled' if s.filled else 'missed'} by {s.object}{truth}: {err} off ({rev.source})"
        v = mine.get(s.target)
        if v is not None:
            said = v.state + ("" if v.error is None else f", {v.error:.1f} nm")
            differs = rev.source == "simulated truth" and (v.state == "filled") != s.filled
            row += f"; the run said {said}" + (" [bold red](differs)[/]" if differs else "")
        table.add_row(f"slot {s.target}", row)
    if more:
        filled = sum(s.filled for s in rev.slots[LISTED:])
        table.add_row("…", f"and {more} more slot(s): {filled} filled, {more - filled} missed "
                           f"(the log holds every one)")
    unfilled, more = first(rev.unfilled)
    for target, reason in unfilled:
        table.add_row(f"unfilled {target}", reason)
    if more:
        table.add_row("…", f"and {more} more unfilled (the log holds every one)")
    causes = Counter(c for _, c in rev.failures)
    table.add_row("pushes (failed)", f"{rev.pushes} ({rev.failed_pushes})")
    if causes:
        table.add_row("failures by cause", ", ".join(f"{k} {c}" for k, c in causes.most_common()))
    if rev.times:
        parts = ", ".join(f"{a.replace('_', ' ')} {_minutes(rev.times.get(a, 0.0))}" for a in ACTIVITIES)
        table.add_row("instrument time", f"{_minutes(rev.total_time)} ({parts})")
    if rev.drift:
        t, dx, dy, sx, sy = rev.drift[-1]
        sigma = "" if math.isnan(sx) else f" +/- ({sx:.1f}, {sy:.1f})"
        off = rev.last_drift_error()
        truth = "" if off is None else f"; {off:.1f} nm from the true drift"
        table.add_row("drift estimate", f"({dx:+.1f}, {dy:+.1f}){sigma} nm at t = {t / 60:.1f} min, "
                                        f"{len(rev.drift)} update(s){truth}")
    console.print(table)


def _incomplete(rev: Review) -> str:
    end = "its start" if rev.end_time is None else f"t = {rev.end_time:.1f} s"
    why = f"; {rev.cut or rev.problem}" if rev.cut or rev.problem else ""
    return f"incomplete: log ends at {end} (after {len(rev.paths)} push(es)){why}"


# -- the plot ----------------------------------------------------------------------------

def plot_review(rev: Review, out: str | os.PathLike) -> None:
    """The review's picture (:func:`nanoasm.review_plot.review_figure`: the scene before and
    after over the full scan, the largest slot errors zoomed, the drift estimate beside the
    truth), written atomically in the format of ``out``'s suffix (png, svg, pdf); in SVG,
    text stays text."""
    from nanoasm.previews import write_figure
    from nanoasm.review_plot import review_figure

    write_figure(review_figure(rev), out)
