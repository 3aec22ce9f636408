"""How far a dry-run or a run is while it runs: timestamped log lines, or a progress bar.

Unattended (stdout not a terminal, or ``--log-level`` given) every step of the run is one
line through :mod:`logging` on stdout, written and flushed as it happens, so a run left
overnight with its output in a file leaves a trail::

    2026-11-26T07:58:28.644+00:00 INFO phase: plan
    2026-11-26T07:58:29.031+00:00 INFO push 1: o5 towards s4, 377 nm of tip path: pushing (peak force 44 nN)

The steps are the run's phases (:data:`~nanoasm.executor.progress_docs.PHASES`), each local
scan, each push (each leg of a push in legs, as the summary counts pushes), and the run's
events: the plan, replans, warnings and errors; ``debug`` adds every push's outcome,
drift estimate and checkpoint. On a terminal (stderr) a rich progress bar shows the phase
and the pushes done against the pushes planned instead. The registration of a layout by
its marks is one line on stderr either way.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext
from datetime import datetime

from nanoasm.errors import InputError

#: ``--log-level`` names and the logging levels they stand for.
LEVELS = {"debug": logging.DEBUG, "info": logging.INFO, "warning": logging.WARNING, "error": logging.ERROR}
#: The logger the lines go through (it does not propagate: they are printed once).
LOGGER = "nanoasm.run"
#: A line: ISO 8601 time with the UTC offset, the level, the message.
FORMAT = "%(asctime)s %(levelname)s %(message)s"
#: Event levels of the run (:class:`~nanoasm.executor.documents.EventDoc`) as logging levels.
EVENT_LEVELS = {"info": logging.INFO, "warn": logging.WARNING, "error": logging.ERROR}
#: The bar shows at most this many characters of what the run said last.
DETAIL = 60

Line = tuple[int, str]


def log_level(name: str | None) -> int | None:
    """The logging level ``--log-level`` names (None: not given); an unknown name is one
    line naming the valid ones."""
    if name is None:
        return None
    level = LEVELS.get(name.lower())
    if level is None:
        raise InputError(None, "--log-level", f"unknown level {name!r}; one of {', '.join(LEVELS)}")
    return level


class RunProgress:
    """How far a run is, from the documents its engine sends (``follow``): its phase,
    the pushes done (as the ledger counts them) and planned, the latest thing it said;
    and the log lines each document makes."""

    def __init__(self, label: str):
        self.label = label
        self.phase: str | None = None
        self.detail = ""
        self.pushes = 0
        self.planned: int | None = None
        self.scans = 0

    def description(self) -> str:
        """The bar's text: ``LABEL: PHASE``, then the latest line of this phase."""
        text = f"{self.label}: {self.phase or 'starting'}"
        detail = self.detail if len(self.detail) <= DETAIL else self.detail[:DETAIL - 1] + "…"
        return f"{text} - {detail}" if detail else text

    def follow(self, topic: str, doc) -> list[Line]:
        """Take in one document; returns the lines it makes, (level, message)."""
        from nanoasm.executor.documents import as_dict

        handler = _HANDLERS.get(topic)
        if handler is None:
            return []
        phase = self.phase
        lines = handler(self, as_dict(doc))
        said = [m for level, m in lines if level >= logging.INFO]
        if said and self.phase == phase:        # a new phase starts with nothing said
            self.detail = said[-1]
        return lines

    def _progress(self, d: dict) -> list[Line]:
        step, text = d["step"], d["text"]
        if step == "phase":
            self.phase, self.detail = text, ""
            return [(logging.INFO, f"phase: {text}")]
        if step == "push":
            self.pushes += 1
            if self.planned is not None:
                self.planned = max(self.planned, self.pushes)
            return [(logging.INFO, f"push {self.pushes}: {text}")]
        self.scans += 1
        return [(logging.INFO, f"local scan {self.scans}: {text}")]

    def _event(self, d: dict) -> list[Line]:
        return [(EVENT_LEVELS.get(d.get("level"), logging.INFO), str(d.get("text", "")))]

    def _plan(self, d: dict) -> list[Line]:
        self.planned = self.pushes + len(d.get("operations") or ())
        return []

    def _checkpoint(self, d: dict) -> list[Line]:
        done, left = int((d.get("counts") or {}).get("pushes", self.pushes)), len(d.get("remaining") or ())
        self.pushes, self.planned = done, done + left
        return [(logging.DEBUG, f"checkpoint: {done} push(es) done, {left} to go")]

    def _push(self, d: dict) -> list[Line]:
        belief = d.get("belief") or {}
        at = belief.get("at") or (float("nan"), float("nan"))
        return [(logging.DEBUG, f"{d['op']['object']}: {d.get('verdict')}, believed at "
                                f"({at[0]:.0f}, {at[1]:.0f}) nm")]

    def _drift(self, d: dict) -> list[Line]:
        off, v = d.get("offset") or (0.0, 0.0), d.get("velocity")
        speed = "" if v is None else f", velocity {v[0]:+.3f}, {v[1]:+.3f} nm/s"
        return [(logging.DEBUG, f"drift estimate: offset {off[0]:+.1f}, {off[1]:+.1f} nm{speed}")]

    def _stop(self, d: dict) -> list[Line]:
        state, reason = d.get("state"), d.get("reason")
        level = {"done": logging.INFO, "aborted": logging.WARNING}.get(state, logging.ERROR)
        return [(level, f"{self.label} {state}: {reason}")]


_HANDLERS: dict[str, Callable[[RunProgress, dict], list[Line]]] = {
    "progress": RunProgress._progress, "event": RunProgress._event, "plan": RunProgress._plan,
    "checkpoint": RunProgress._checkpoint, "push": RunProgress._push, "drift": RunProgress._drift,
    "stop": RunProgress._stop,
}


class _Stdout(logging.StreamHandler):
    """Lines to whatever ``sys.stdout`` is when each is written (a redirect, a capture),
    flushed after each."""

    @property
    def stream(self):
        return sys.stdout

    @stream.setter
    def stream(self, value) -> None:
        pass


class IsoFormatter(logging.Formatter):
    """:data:`FORMAT` with the time as ISO 8601, to the millisecond, with the UTC offset."""

    def __init__(self):
        super().__init__(FORMAT)

    def formatTime(self, record: logging.LogRecord, datefmt: str | None = None) -> str:  # noqa: N802
        return datetime.fromtimestamp(record.created).astimezone().isoformat(timespec="milliseconds")


@contextmanager
def log_lines(level: int) -> Iterator[logging.Logger]:
    """The run's logger writing lines of ``level`` and above to stdout while in the block."""
    logger = logging.getLogger(LOGGER)
    handler = _Stdout()
    handler.setFormatter(IsoFormatter())
    before = logger.level, logger.propagate
    logger.setLevel(level)
    logger.propagate = False
    logger.addHandler(handler)
    try:
        yield logger
    finally:
        logger.removeHandler(handler)
        logger.setLevel(before[0])
        logger.propagate = before[1]


def progress_bar(console):
    """The rich bar: the phase and what was said last, pushes done against planned, the time.
    Stdout is left alone (log lines redirected to a file stay there), stderr's lines are
    shown above the bar."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TextColumn("push(es)"),
                    TimeElapsedColumn(), console=console, transient=True, redirect_stdout=False)


def run_progress(label: str, level_name: str | None = None) -> AbstractContextManager[list]:
    """Engine subscribers showing how far the run is (``label``: "dry-run" or "run"): log
    lines when stdout is not a terminal or ``level_name`` (``--log-level``) is given, a
    progress bar on a terminal otherwise; and the registration of a layout by its marks
    in one line on stderr. The level is checked here, before the run."""
    level = log_level(level_name)
    lines = level is not None or not sys.stdout.isatty()
    return _run_progress(label, level if level is not None else logging.INFO, lines)


@contextmanager
def _run_progress(label: str, level: int, lines: bool) -> Iterator[list]:
    from rich.console import Console

    console = Console(stderr=True)
    state = RunProgress(label)

    def registered(topic: str, doc) -> None:
        if topic == "registration":
            from nanoasm.executor.documents import as_dict

            console.print(f"nanoasm: {as_dict(doc)['text']}", markup=False, highlight=False, soft_wrap=True)

    bar = console.is_terminal and not (lines and sys.stdout.isatty())     # never two on one terminal
    with (log_lines(level) if lines else nullcontext()) as logger, (progress_bar(console) if bar else nullcontext()) as shown:
        task = None if shown is None else shown.add_task(state.description(), total=None)

        def follow(topic: str, doc) -> None:
            if topic not in _HANDLERS:
                return
            for at, message in state.follow(topic, doc):
                if logger is not None:
                    logger.log(at, message)
            if shown is not None:
                shown.update(task, description=state.description(), completed=state.pushes, total=state.planned)

        yield [follow, registered]

