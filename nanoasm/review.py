"""``nanoasm review run.mcap``: what a logged dry-run or run did, as a table and a plot.

Everything comes from the log (:func:`nanoasm.executor.logread.read_log`): the layout
attachment, the plan, the pushes, checkpoints and the executor's belief, the drift
estimate, and in a dry-run the simulated truth the harness added (``/sim/truth``). A slot's
error is measured against that truth when the log has it, else against the executor's
last belief. A log cut short (a killed process) is reviewed as far as it goes.
"""

from __future__ import annotations

import io
import math
import os
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from nanoasm.bodies import Body
from nanoasm.errors import InputError
from nanoasm.executor.runlog import FAILED_VERDICTS

ACTIVITIES = ("full_scan", "local_scan", "push", "travel")


@dataclass(frozen=True)
class SlotRow:
    target: str
    object: str | None
    error: float | None        # centre error, nm (None: no pose known)
    filled: bool


@dataclass
class Review:
    """A run log's figures."""

    path: str
    complete: bool
    problem: str | None
    kind: str                                  # "dry-run" or "run"
    metadata: dict[str, str]
    end_time: float | None
    stop: dict | None = None
    layout: Any = None
    source: str = "belief"                     # what slot errors are measured against
    slots: list[SlotRow] = field(default_factory=list)
    unfilled: list[tuple[str, str]] = field(default_factory=list)
    pushes: int = 0
    failed_pushes: int = 0
    failures: list[tuple[str, str]] = field(default_factory=list)   # (object, cause)
    times: dict[str, float] = field(default_factory=dict)
    total_time: float | None = None
    drift: list[tuple[float, float, float, float, float]] = field(default_factory=list)  # t dx dy sx sy
    initial: list[Body] = field(default_factory=list)     # identified objects
    final: list[Body] = field(default_factory=list)       # last belief
    truth_initial: list[Body] = field(default_factory=list)
    truth_final: list[Body] = field(default_factory=list)
    paths: list[tuple[list, str]] = field(default_factory=list)   # (tip path, verdict)

    @property
    def filled(self) -> int:
        return sum(s.filled for s in self.slots)


def _body(d: Any) -> Body | None:
    try:
        angle, length = d.get("angle"), d.get("length")
        elongated = d["kind"] in ("rod", "wire")
        return Body(str(d["id"]), str(d["kind"]), (float(d["at"][0]), float(d["at"][1])), float(d["diameter"]),
                    float(angle) if elongated else None, float(length) if elongated else None)
    except (AttributeError, KeyError, TypeError, ValueError, IndexError):
        return None


def _bodies(docs: Any) -> list[Body]:
    return [b for b in map(_body, docs if isinstance(docs, list) else ()) if b is not None]


def _pairs(docs: Any, a: str, b: str) -> list[tuple[str, str]]:
    out = []
    for d in docs if isinstance(docs, list) else ():
        if isinstance(d, dict) and a in d and b in d:
            out.append((str(d[a]), str(d[b])))
        elif isinstance(d, (list, tuple)) and len(d) == 2:
            out.append((str(d[0]), str(d[1])))
    return out


def review(path: str | os.PathLike) -> Review:
    """Read and summarise a run log; raises InputError for a file that is no run log."""
    from nanoasm.cad.layout import layout_from_dict
    from nanoasm.executor.logread import read_log

    log = read_log(path)
    meta = dict(log.metadata.get("nanoasm", {}))
    kind = "dry-run" if "dry-run" in log.metadata or log.topic("/sim/truth") else meta.get("kind", "run")
    rev = Review(str(path), log.complete, log.problem, kind, meta, log.end_time)
    if "nanoasm" not in log.metadata and log.complete:
        raise InputError(str(path), None, "an MCAP file, but not a nanoasm run log (no 'nanoasm' metadata)")
    layout_doc = log.attachment_json("layout.json")
    if isinstance(layout_doc, dict):
        try:
            rev.layout = layout_from_dict(layout_doc, "layout.json")
        except (InputError, ValueError):
            rev.layout = None
    stop = log.last("/stop")
    rev.stop = stop.data if stop is not None and isinstance(stop.data, dict) else None

    # the executor's belief, replayed: identified objects, then pushes and checkpoints
    env = log.last("/environment")
    rev.initial = _bodies(env.data.get("objects")) if env is not None and isinstance(env.data, dict) else []
    belief = {b.id: b for b in rev.initial}
    lost: set[str] = set()
    checkpoint = None
    for m in log.messages:
        if not isinstance(m.data, dict):
            continue
        if m.topic == "/push":
            b = _body(m.data.get("belief"))
            if b is not None:
                belief[b.id] = b
            op = m.data.get("op") if isinstance(m.data.get("op"), dict) else {}
            rev.paths.append((op.get("tip_path") or [], str(m.data.get("verdict", ""))))
        elif m.topic == "/checkpoint":
            checkpoint = m.data
            bd = m.data.get("belief") if isinstance(m.data.get("belief"), dict) else {}
            belief = {b.id: b for b in _bodies(bd.get("objects"))} or belief
            lost = set(bd.get("lost") or ())
        elif m.topic == "/drift":
            _drift_row(rev, m.t, m.data)
    rev.final = [b for oid, b in belief.items() if oid not in lost]

    # what the run did: its result when it got that far, else the last checkpoint
    result = log.last("/result")
    res = result.data if result is not None and isinstance(result.data, dict) else None
    plan = log.last("/plan")
    plan_doc = plan.data if plan is not None and isinstance(plan.data, dict) else {}
    source = res if res is not None else plan_doc
    assignment = _pairs(source.get("assignment"), "target", "object")
    rev.unfilled = _pairs(source.get("unfilled"), "target", "reason")
    counts = (res or checkpoint or {}).get("counts") or {}
    rev.pushes = int(counts.get("pushes", len(rev.paths))) if isinstance(counts, dict) else len(rev.paths)
    failed = [m for m in log.topic("/push") if isinstance(m.data, dict) and m.data.get("verdict") in FAILED_VERDICTS]
    rev.failed_pushes = int(counts.get("failed_pushes", len(failed))) if isinstance(counts, dict) else len(failed)
    if res is not None:
        rev.failures = _pairs(res.get("failures"), "object", "cause")
    else:
        rev.failures = [(str(o), "lost") for o in sorted(lost)]
        rev.failures += [(str((m.data.get("op") or {}).get("object")), str(m.data["verdict"])) for m in failed]
    times = (res or checkpoint or {}).get("times") or {}
    rev.times = {a: float(times.get(a, 0.0)) for a in ACTIVITIES} if isinstance(times, dict) else {}
    starts = [m.t for m in log.topic("/events")]
    if res is not None and isinstance(res.get("epoch"), (int, float)):
        starts.append(float(res["epoch"]))
    if starts and rev.end_time is not None:
        rev.total_time = rev.end_time - min(starts)

    # slots: against the simulated truth when the harness logged it, else the last belief
    truth = {m.data.get("phase"): m.data for m in log.topic("/sim/truth") if isinstance(m.data, dict)}
    final = {b.id: b for b in rev.final}
    if "initial" in truth:
        rev.truth_initial = _bodies(truth["initial"].get("objects"))
    if "final" in truth:
        rev.truth_final = _bodies(truth["final"].get("objects"))
        ids = truth["final"].get("ids") if isinstance(truth["final"].get("ids"), dict) else {}
        assignment = [(t, str(ids.get(o, o))) for t, o in assignment]
        final = {b.id: b for b in rev.truth_final}
        rev.source = "simulated truth"
    if rev.layout is not None:
        rev.slots = _slots(rev.layout, assignment, final)
    return rev


def _drift_row(rev: Review, t: float, doc: dict) -> None:
    try:
        dx, dy = (float(v) for v in doc["offset"])
        cov = doc.get("cov")
        sx, sy = (math.sqrt(max(float(cov[0][0]), 0.0)), math.sqrt(max(float(cov[1][1]), 0.0))) if cov else \
            (math.nan, math.nan)
    except (KeyError, TypeError, ValueError, IndexError):
        return
    rev.drift.append((float(doc.get("t", t)), dx, dy, sx, sy))


def _slots(layout, assignment: list[tuple[str, str]], final: dict[str, Body]) -> list[SlotRow]:
    from nanoasm.dryrun import filled_slots
    from nanoasm.planner.plan import Assignment

    known = {t.id for t in layout.targets}
    pairs = [Assignment(t, o) for t, o in assignment if t in known]
    filled, errors = filled_slots(layout, pairs, final)
    return [SlotRow(a.target, a.object, errors.get(a.target), a.target in filled) for a in pairs]


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
    if not rev.complete:
        table.add_row("[bold red]incomplete[/]", _incomplete(rev))
    elif rev.stop is not None and rev.stop.get("state") != "done":
        table.add_row("[bold red]stopped[/]", f"{rev.stop.get('state')}: {rev.stop.get('reason')}")
    for k in ("strategy", "seed", "command", "resumed_from"):
        if rev.metadata.get(k):
            table.add_row(k.replace("_", " "), rev.metadata[k])
    for s in rev.slots:
        err = "no pose" if s.error is None else f"{s.error:.1f} nm"
        table.add_row(f"slot {s.target}", f"{'filled' if s.filled else 'missed'} by {s.object}: {err} off "
                                          f"({rev.source})")
    for target, reason in rev.unfilled:
        table.add_row(f"unfilled {target}", reason)
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
        table.add_row("drift estimate", f"({dx:+.1f}, {dy:+.1f}){sigma} nm at t = {t / 60:.1f} min, "
                                        f"{len(rev.drift)} update(s)")
    console.print(table)


def _incomplete(rev: Review) -> str:
    end = "its start" if rev.end_time is None else f"t = {rev.end_time:.1f} s"
    why = f"; {rev.problem}" if rev.problem else ""
    return f"incomplete: log ends at {end} (after {len(rev.paths)} push(es)){why}"


# -- the plot ----------------------------------------------------------------------------

def plot_review(rev: Review, out: str | os.PathLike) -> None:
    """Before/after scene with the push paths, and the drift estimate over time (±σ);
    written atomically, in the format of ``out``'s suffix (png, svg, pdf)."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    from nanoasm.fileio import write_atomic

    fig, axes = plt.subplots(1, 3, figsize=(16, 5.5))
    before, after, drift = axes
    _scene(before, rev, rev.initial, rev.truth_initial, "before: identified" +
           (" (truth dotted)" if rev.truth_initial else ""), paths=False)
    _scene(after, rev, rev.final, rev.truth_final, "after: belief" +
           (" (truth dotted)" if rev.truth_final else "") + ", push paths", paths=True)
    if rev.drift:
        t = [r[0] / 60 for r in rev.drift]
        for i, (label, colour) in enumerate((("dx", "tab:blue"), ("dy", "tab:orange"))):
            v = [r[1 + i] for r in rev.drift]
            s = [r[3 + i] for r in rev.drift]
            drift.plot(t, v, color=colour, label=label)
            if not all(math.isnan(x) for x in s):
                drift.fill_between(t, [a - b for a, b in zip(v, s)], [a + b for a, b in zip(v, s)],
                                   color=colour, alpha=0.25, label=f"{label} +/- sigma")
        drift.legend()
    else:
        drift.text(0.5, 0.5, "no drift estimate in the log", ha="center", va="center", transform=drift.transAxes)
    drift.set_xlabel("instrument time, min")
    drift.set_ylabel("drift, nm")
    drift.set_title("drift estimate")
    status = "" if rev.complete else " (incomplete log)"
    fig.suptitle(f"{os.path.basename(rev.path)}: {rev.filled} slot(s) filled, {rev.pushes} push(es){status}")
    fig.tight_layout()
    buf = io.BytesIO()
    fmt = os.path.splitext(str(out))[1].lstrip(".").lower() or "png"
    fig.savefig(buf, format=fmt, dpi=110)
    plt.close(fig)
    write_atomic(out, buf.getvalue())


def _scene(ax, rev: Review, bodies: list[Body], truth: list[Body], title: str, *, paths: bool) -> None:
    from matplotlib.patches import Polygon

    if rev.layout is not None:
        w, h = rev.layout.area
        ax.plot([0, w, w, 0, 0], [0, 0, h, h, 0], color="0.6", lw=0.8)
        for k in rev.layout.keepouts:
            ax.add_patch(Polygon(k.polygon, closed=True, fc=(1, 0.3, 0.3, 0.15), ec="tab:red", lw=0.8))
        for tg in rev.layout.targets:
            _outline(ax, tg, ec="tab:blue", ls="-", lw=1.2)
            ax.annotate(tg.id, tg.at, color="tab:blue", fontsize=7, ha="center", va="center")
    for b in truth:
        _outline(ax, b, ec="tab:purple", ls=":", lw=1.0)
    for b in bodies:
        _outline(ax, b, ec="black", ls="-", lw=0.8, fc=(1.0, 0.8, 0.2, 0.6))
    if paths:
        for pts, verdict in rev.paths:
            if len(pts) >= 2:
                xs, ys = zip(*((p[0], p[1]) for p in pts))
                colour = "tab:red" if verdict in FAILED_VERDICTS else "tab:green"
                ax.plot(xs, ys, color=colour, lw=1.0)
                ax.plot(xs[-1], ys[-1], marker=".", color=colour)
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_title(title)
    ax.set_xlabel("x, nm")
    ax.set_ylabel("y, nm")


def _outline(ax, b: Body, **style) -> None:
    from matplotlib.patches import Polygon

    ring = b.geometry().buffer(b.radius, quad_segs=8).exterior.coords
    style.setdefault("fc", "none")
    ax.add_patch(Polygon(list(ring), closed=True, **style))
