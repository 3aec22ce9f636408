"""The run engine: procedures are generators of messages, the engine carries them out.

As in bluesky, a procedure (see :mod:`nanoasm.executor.assembly`) never touches the
instrument: it ``yield``\\ s :class:`Msg` objects and receives their results. The engine
executes each against an :class:`~nanoasm.instrument.Instrument`, tells its
subscribers about events and checkpoints, and moves through an explicit state
machine::

    IDLE --run--> RUNNING --procedure returns--> DONE
                     |---- exception ---------> FAILED
                     '---- Ctrl-C / SIGTERM ---> ABORTED

On every exit, whatever the state, the tip is lifted and the DAC parked
(``instrument.park()``), the subscribers are told how the run ended and closed. A
further Ctrl-C or SIGTERM during that clean-up waits for its end (:mod:`.stopping`).
"""

from __future__ import annotations

import enum
import time
from collections.abc import Callable, Generator
from dataclasses import dataclass, field
from typing import Any

from nanoasm.instrument import Instrument

from .documents import CHECKPOINT, EVENT, STOP, Document, EventDoc, StopDoc
from .stopping import StopSignals

#: Commands a procedure may yield, and what each returns.
COMMANDS = {
    "write": "SignalBlock of the streamed DAC chunk",
    "full_scan": "HeightImage",
    "scan_line": "(n,) heights",
    "signals": "(S_n, S_l)",
    "clock": "instrument seconds",
    "position": "(3,) DAC codes of the present output",
    "park": "None",
    "checkpoint": "None (subscribers keep the state for resuming)",
    "event": "None (a log line for subscribers)",
    "emit": "None (a document on a topic for subscribers)",
}


@dataclass(frozen=True)
class Msg:
    """One instruction of a procedure: ``command`` (see :data:`COMMANDS`) and its arguments."""

    command: str
    args: tuple = ()
    kwargs: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.command not in COMMANDS:
            raise ValueError(f"unknown command {self.command!r}; one of {', '.join(COMMANDS)}")


class RunState(enum.Enum):
    IDLE = "idle"
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"
    ABORTED = "aborted"


class Terminated(BaseException):
    """Raised in the main thread when the process receives SIGTERM."""

    stop_reason = "terminated (SIGTERM)"


Subscriber = Callable[[str, Document], None]


class RunEngine:
    """Executes procedures against ``instrument`` for ``subscribers(topic, document)``.

    Topics sent (:mod:`.documents`): ``event`` (:class:`~.documents.EventDoc`),
    ``checkpoint`` (the procedure's state), any topic a procedure ``emit``\\ s, and
    ``stop`` (:class:`~.documents.StopDoc`) once, at the end. Subscribers with a
    ``close()`` method are closed after ``stop``.
    """

    def __init__(self, instrument: Instrument, subscribers: list[Subscriber] | None = None):
        if not isinstance(instrument, Instrument):
            raise TypeError(f"{type(instrument).__name__} does not implement the Instrument protocol")
        self.instrument = instrument
        self.subscribers = list(subscribers or [])
        self.state = RunState.IDLE
        self.reason = ""
        self.messages = 0
        self.wall_time = 0.0

    def subscribe(self, fn: Subscriber) -> None:
        self.subscribers.append(fn)

    def _tell(self, topic: str, doc: Document) -> None:
        for fn in self.subscribers:
            fn(topic, doc)

    def _dispatch(self, msg: Msg) -> Any:
        inst = self.instrument
        c = msg.command
        if c == "write":
            return inst.write(*msg.args, **msg.kwargs)
        if c == "full_scan":
            return inst.full_scan(*msg.args, **msg.kwargs)
        if c == "scan_line":
            return inst.scan_line(*msg.args, **msg.kwargs)
        if c == "signals":
            return inst.signals()
        if c == "clock":
            return inst.clock()
        if c == "position":
            return inst.position()
        if c == "park":
            return inst.park()
        if c == "checkpoint":
            self._tell(CHECKPOINT, msg.args[0] if msg.args else dict(msg.kwargs))
            return None
        if c == "event":
            text = msg.args[0] if msg.args else ""
            self._tell(EVENT, EventDoc(inst.clock(), msg.kwargs.get("level", "info"), text))
            return None
        topic, doc = msg.args
        self._tell(topic, doc)
        return None

    def run(self, procedure: Generator[Msg, Any, Any]) -> Any:
        """Run ``procedure`` to its end; returns its return value.

        Exceptions from the procedure or the instrument propagate after the clean-up;
        Ctrl-C arrives as KeyboardInterrupt, SIGTERM as :class:`Terminated`, and another
        during the clean-up is held until it ends (raised then if the run had completed).
        """
        if self.state is not RunState.IDLE:
            raise RuntimeError(f"a run engine runs once; this one is {self.state.value}")
        signals = StopSignals(Terminated)
        signals.install()
        self.state = RunState.RUNNING
        t0 = time.perf_counter()
        try:
            reply: Any = None
            while True:
                try:
                    msg = procedure.send(reply)
                except StopIteration as stop:
                    self.state, self.reason = RunState.DONE, "completed"
                    return stop.value
                if not isinstance(msg, Msg):
                    raise TypeError(f"a procedure must yield Msg objects, got {type(msg).__name__}")
                self.messages += 1
                signals.check()                 # a Ctrl-C whose exception was swallowed stops the run here
                reply = self._dispatch(msg)
        except (KeyboardInterrupt, Terminated) as exc:
            signals.stopping = True             # first: a further signal is held from here on
            self.state = RunState.ABORTED
            self.reason = "interrupted (Ctrl-C)" if isinstance(exc, KeyboardInterrupt) else exc.stop_reason
            raise
        except BaseException as exc:
            signals.stopping = True
            self.state, self.reason = RunState.FAILED, f"{type(exc).__name__}: {exc}"
            raise
        finally:
            signals.stopping = True
            self.wall_time = time.perf_counter() - t0
            try:
                self._clean_up(procedure)
            finally:
                signals.restore(by_signal=self.state is RunState.ABORTED)
            if self.state is RunState.DONE:
                signals.raise_held()

    def _clean_up(self, procedure: Generator) -> None:
        """Park the instrument and close everything, whatever happened."""
        try:
            procedure.close()
        finally:
            try:
                self.instrument.park()
            finally:
                try:
                    self._tell(STOP, StopDoc(self.state.value, self.reason))
                finally:
                    for fn in self.subscribers:
                        close = getattr(fn, "close", None)
                        if callable(close):
                            close()
