"""The run engine: messages, states, and clean-up on every way out."""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest

from nanoasm.executor.documents import CHECKPOINT, EVENT, STOP, EventDoc, StopDoc
from nanoasm.executor.engine import Msg, RunEngine, RunState, Terminated
from nanoasm.instrument import HeightImage, InstrumentConfig, SignalBlock, check_samples, ramp


class Stage:
    """A stage with no sample: records what happens to it."""

    def __init__(self) -> None:
        self._config = InstrumentConfig()
        self._t = 0.0
        self._last = self._config.rest_codes()
        self.parked = 0
        self.written = 0

    @property
    def config(self):
        return self._config

    def clock(self):
        return self._t

    def write(self, chunk):
        c = check_samples(chunk, self._config, previous=self._last)
        t = self._t + np.arange(1, len(c) + 1) / self._config.sample_rate
        self._t, self._last = float(t[-1]), c[-1]
        self.written += len(c)
        return SignalBlock(t, np.zeros(len(c)), np.zeros(len(c)))

    def full_scan(self, pixels, region=None):
        self._t += pixels
        return HeightImage(np.zeros((pixels, pixels)), 10.0, source="stage")

    def scan_line(self, a, b, n):
        self._t += 0.2
        return np.zeros(n)

    def signals(self):
        return 0.0, 0.0

    def position(self):
        return self._last.copy()

    def park(self):
        self.parked += 1
        path = ramp(self._last, self._config.rest_codes(), self._config)
        if len(path):
            self.write(path)


class Recorder:
    def __init__(self):
        self.docs = []
        self.closed = False

    def __call__(self, topic, doc):
        self.docs.append((topic, doc))

    def close(self):
        self.closed = True


def away(stage: Stage):
    """A procedure that moves the tip away from rest, lowered, then keeps going."""
    here = yield Msg("position")
    target = here.copy()
    target[0] += 2000
    target[2] = stage.config.nm_to_codes(np.array([0.0, 0.0, -50.0]))[2]
    yield Msg("write", (ramp(here, target, stage.config),))
    yield Msg("event", ("moved",))
    yield Msg("checkpoint", ({"done": 1},))
    return "finished"


def test_a_procedure_runs_and_the_instrument_is_parked():
    stage, rec = Stage(), Recorder()
    engine = RunEngine(stage, [rec])
    assert engine.run(away(stage)) == "finished"
    assert engine.state is RunState.DONE
    assert stage.parked == 1 and np.array_equal(stage.position(), stage.config.rest_codes())
    topics = [t for t, _ in rec.docs]
    assert topics == [EVENT, CHECKPOINT, STOP] and rec.closed
    event = rec.docs[0][1]          # stamped with the instrument's clock after the move
    assert event == EventDoc(event.t, "info", "moved") and 0.0 < event.t < stage.clock()
    assert rec.docs[1][1] == {"done": 1}
    assert rec.docs[-1][1] == StopDoc("done", "completed")


def failing(stage, exc):
    yield from away(stage)
    raise exc


@pytest.mark.parametrize("exc,state", [(RuntimeError("boom"), RunState.FAILED),
                                       (KeyboardInterrupt(), RunState.ABORTED)])
def test_errors_and_ctrl_c_still_park_and_close(exc, state):
    stage, rec = Stage(), Recorder()
    engine = RunEngine(stage, [rec])
    with pytest.raises(type(exc)):
        engine.run(failing(stage, exc))
    assert engine.state is state
    assert stage.parked == 1 and np.array_equal(stage.position(), stage.config.rest_codes())
    assert rec.closed and rec.docs[-1][0] == STOP and rec.docs[-1][1].state == state.value


def test_sigterm_parks_and_the_old_handler_comes_back():
    stage, rec = Stage(), Recorder()
    before = signal.getsignal(signal.SIGTERM)

    def killed():
        yield from away(stage)
        os.kill(os.getpid(), signal.SIGTERM)
        yield Msg("clock")
        raise AssertionError("SIGTERM did not stop the run")

    engine = RunEngine(stage, [rec])
    with pytest.raises(Terminated):
        engine.run(killed())
    assert engine.state is RunState.ABORTED and "SIGTERM" in engine.reason
    assert stage.parked == 1 and rec.closed
    assert signal.getsignal(signal.SIGTERM) == before


def test_an_instrument_error_fails_the_run_cleanly():
    stage = Stage()

    def too_fast():
        here = yield Msg("position")
        jump = here.copy()
        jump[0] += 10_000           # one sample far beyond the slew limit
        yield Msg("write", (jump[None, :],))

    engine = RunEngine(stage)
    from nanoasm.errors import InstrumentLimitError

    with pytest.raises(InstrumentLimitError):
        engine.run(too_fast())
    assert engine.state is RunState.FAILED and stage.parked == 1 and stage.written == 0


def test_messages_are_checked():
    with pytest.raises(ValueError, match="unknown command"):
        Msg("teleport")
    engine = RunEngine(Stage())

    def bad():
        yield "write"

    with pytest.raises(TypeError, match="Msg objects"):
        engine.run(bad())
    with pytest.raises(RuntimeError, match="runs once"):
        engine.run(away(Stage()))
    with pytest.raises(TypeError, match="Instrument protocol"):
        RunEngine(object())
