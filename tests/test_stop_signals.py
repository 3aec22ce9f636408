"""A second Ctrl-C (or SIGTERM) while a run stops cannot cut its log's /stop record or its
closing (issue 15, signals): it is held until the clean-up ends."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest
from runlogkit import cli_env, particle_bowtie, stop_when
from test_engine import Recorder, Stage, away

from nanoasm.examples import path as example
from nanoasm.executor.documents import STOP
from nanoasm.executor.engine import Msg, RunEngine, RunState, Terminated
from nanoasm.executor.logread import read_log
from nanoasm.executor.resume import resume_point
from nanoasm.simkeep import read_sim_state, sim_state_path


@pytest.fixture(autouse=True)
def _ctrl_c_as_in_a_terminal():
    """Ctrl-C raises KeyboardInterrupt here, as in a program started from a terminal: a
    shell that starts the tests in the background (``cmd &``, nohup) starts them with
    SIGINT ignored, and a run keeps it so (test_an_ignored_ctrl_c_stays_ignored). These
    tests failed in a clean-clone CI started that way."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


class SlowToClose(Recorder):
    """A subscriber that receives ``signum`` while it closes (as a log does while it
    writes its summary), then finishes closing."""

    def __init__(self, signum: int):
        super().__init__()
        self.signum = signum

    def close(self):
        os.kill(os.getpid(), self.signum)
        time.sleep(0.05)                  # the handler runs here, or at the next bytecode
        self.closed = True


def _interrupted(stage):
    yield from away(stage)
    os.kill(os.getpid(), signal.SIGINT)
    yield Msg("clock")
    raise AssertionError("Ctrl-C did not stop the run")


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_second_signal_while_a_stopped_run_cleans_up_is_held(signum):
    stage, rec = Stage(), SlowToClose(signum)
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    engine = RunEngine(stage, [rec])
    with pytest.raises(KeyboardInterrupt):          # the first signal's, not the second's
        engine.run(_interrupted(stage))
    assert engine.state is RunState.ABORTED and engine.reason == "interrupted (Ctrl-C)"
    assert rec.closed and rec.docs[-1][0] == STOP and rec.docs[-1][1].state == "aborted"
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before


@pytest.mark.parametrize("signum,raised", [(signal.SIGINT, KeyboardInterrupt), (signal.SIGTERM, Terminated)])
def test_a_signal_while_a_completed_run_closes_waits_for_the_close(signum, raised):
    stage, rec = Stage(), SlowToClose(signum)
    engine = RunEngine(stage, [rec])
    with pytest.raises(raised):
        engine.run(away(stage))
    assert engine.state is RunState.DONE and rec.closed and rec.docs[-1][1].state == "done"


def _swallow_ctrl_c():
    try:
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
    except KeyboardInterrupt:
        pass


def test_a_ctrl_c_swallowed_by_library_code_stops_the_run_at_its_next_message():
    """Code that calls back into Python and clears its errors may swallow the
    KeyboardInterrupt (seen in a simulated push), and two Ctrl-C a millisecond apart may
    reach Python as one (a run in CI went on to its end): the engine raises it again."""
    stage, rec = Stage(), Recorder()

    def swallowing():
        yield from away(stage)
        _swallow_ctrl_c()
        yield Msg("clock")
        raise AssertionError("a swallowed Ctrl-C did not stop the run")

    engine = RunEngine(stage, [rec])
    with pytest.raises(KeyboardInterrupt):
        engine.run(swallowing())
    assert engine.state is RunState.ABORTED and rec.closed and rec.docs[-1][1].state == "aborted"


def test_a_ctrl_c_while_a_module_loads_lets_the_import_end_and_stops_the_run_next(tmp_path, monkeypatch):
    """An extension module that calls back into Python while it loads cannot carry an
    exception out of its initialisation (a CI run aborted with a Ctrl-C in OMPL's first
    import): a signal that arrives inside an import is raised once the import has ended
    (delivered again, or at the engine's next message)."""
    (tmp_path / "slow_to_load.py").write_text(
        "import os, signal, time\n"
        "os.kill(os.getpid(), signal.SIGINT)\n"
        "time.sleep(0.05)\n"
        "LOADED = True\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    stage, rec = Stage(), Recorder()
    seen = []

    def importing():
        yield from away(stage)
        import slow_to_load
        seen.append(slow_to_load.LOADED)
        yield Msg("clock")
        raise AssertionError("a Ctrl-C held through an import did not stop the run")

    engine = RunEngine(stage, [rec])
    try:
        with pytest.raises(KeyboardInterrupt):
            engine.run(importing())
    finally:
        sys.modules.pop("slow_to_load", None)
    assert seen == [True]
    assert engine.state is RunState.ABORTED and rec.closed and rec.docs[-1][1].state == "aborted"


# The Ctrl-C is timed from just before the import, inside the try: a timer started before it
# could fire while Thread.start() still waited for its thread (a loaded machine, the suite on
# two workers: KeyboardInterrupt outside the try, exit -2).
OMPL_IMPORT_INTERRUPTED = """
import os, signal, sys, threading, time
from nanoasm.executor.stopping import interrupt_outside_imports
signal.signal(signal.SIGINT, interrupt_outside_imports)
go = threading.Event()

def ctrl_c():
    go.wait()
    time.sleep(float(sys.argv[1]))
    os.kill(os.getpid(), signal.SIGINT)

threading.Thread(target=ctrl_c, daemon=True).start()
loaded = False
try:
    go.set()
    import ompl.base, ompl.geometric
    loaded = True
    time.sleep(1.0)
except KeyboardInterrupt:
    sys.exit(7 if loaded else 8)
sys.exit(9)
"""


@pytest.mark.parametrize("delay", [0.002, 0.005, 0.01])
def test_a_program_interrupted_in_ompls_import_gets_its_ctrl_c_after_it(delay, tmp_path):
    """Python's own handler raises in OMPL's module initialisation, and the process
    aborts (SIGABRT: 'terminate called after throwing nanobind::python_error'); with
    interrupt_outside_imports, the import ends and Ctrl-C is raised after it."""
    # not in the repository's root, whose nanoasm/ folder is not the installed package
    proc = subprocess.run([sys.executable, "-c", OMPL_IMPORT_INTERRUPTED, str(delay)], env=cli_env(), cwd=tmp_path,
                          capture_output=True, text=True, timeout=60,
                          preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert proc.returncode == 7, proc.stderr[-2000:]


def test_a_ctrl_c_swallowed_in_a_runs_last_step_is_raised_after_its_clean_up():
    stage, rec = Stage(), Recorder()

    def last():
        yield from away(stage)
        _swallow_ctrl_c()
        return "finished"

    engine = RunEngine(stage, [rec])
    with pytest.raises(KeyboardInterrupt):
        engine.run(last())
    assert engine.state is RunState.DONE and rec.closed and rec.docs[-1][1].state == "done"
    engine = RunEngine(Stage(), [Recorder()])          # and the next run is not stopped by it
    assert engine.run(_finishing()) == "finished"


def _finishing():
    yield Msg("clock")
    return "finished"


def test_an_ignored_ctrl_c_stays_ignored():
    """A sweep's workers ignore SIGINT (their parent handles it): a run keeps it so."""
    stage, rec = Stage(), Recorder()
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        def ignored():
            yield from away(stage)
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
            return "finished"

        assert RunEngine(stage, [rec]).run(ignored()) == "finished"
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)


@pytest.mark.parametrize("gap", [0.001, 0.005])
def test_two_ctrl_c_a_few_ms_apart_leave_a_closed_resumable_log_and_one_line(tmp_path, gap):
    """The second Ctrl-C lands in the run's clean-up (held) or while the command ends
    (ignored: it used to end the process with exit -2)."""
    _, layout = particle_bowtie()
    layout.save(tmp_path / "particles.toml")
    log = tmp_path / "run.mcap"
    # a shell may start us with SIGINT ignored, which the child would inherit
    proc = subprocess.Popen([sys.executable, "-m", "nanoasm.cli", "dry-run", str(example("bowtie_scene.toml")),
                             "particles.toml", "--seed", "3", "--log", str(log)], cwd=tmp_path, env=cli_env(),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    # once the first checkpoint is logged and its world kept
    err = stop_when(proc, sim_state_path(log).exists, [(0.0, signal.SIGINT), (gap, signal.SIGINT)])
    assert proc.returncode == 130 and "Traceback" not in err, err
    assert err.strip().splitlines() == [f"{log}: written", "nanoasm: interrupted"], err
    contents = read_log(log)
    assert contents.complete, contents.problem
    assert [m.data["reason"] for m in contents.topic("/stop")] == ["interrupted (Ctrl-C)"]
    point = resume_point(log, "dry-run", at=read_sim_state(sim_state_path(log))["t"])
    assert point.state["remaining"]


def test_a_program_that_ends_on_a_stop_keeps_further_signals_ignored():
    """With ignore_after_stop (the nanoasm command), a run stopped by Ctrl-C leaves SIGINT
    and SIGTERM ignored: a second Ctrl-C cannot cut the lines the command prints after
    the run (the log's 'written' line went missing in CI when it landed there)."""
    from nanoasm.executor.stopping import ignore_after_stop

    stage, rec = Stage(), Recorder()
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    ignore_after_stop()
    try:
        with pytest.raises(KeyboardInterrupt):
            RunEngine(stage, [rec]).run(_interrupted(stage))
        assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == (signal.SIG_IGN, signal.SIG_IGN)
        os.kill(os.getpid(), signal.SIGINT)         # ignored: nothing raised
        time.sleep(0.01)
        # a run that completes restores them as ever
        signal.signal(signal.SIGINT, before[0])
        signal.signal(signal.SIGTERM, before[1])
        done = Stage()
        engine = RunEngine(done, [Recorder()])
        engine.run(away(done))
        assert engine.state is RunState.DONE
        assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
    finally:
        ignore_after_stop(False)
        signal.signal(signal.SIGINT, before[0])
        signal.signal(signal.SIGTERM, before[1])
