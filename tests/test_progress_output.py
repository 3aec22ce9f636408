"""Unattended output (issue 17 item 5): a dry-run whose stdout is not a terminal says how
it goes in timestamped log lines, one per phase, local scan, push and event, flushed as
they happen; ``--log-level`` chooses how much; on a terminal a bar names the phase."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time

import pytest

from nanoasm import progress
from nanoasm.cli import main
from nanoasm.examples import path as example
from nanoasm.executor.progress_docs import PHASES

#: A log line: ISO 8601 time to the millisecond with its UTC offset, the level, the message.
LINE = re.compile(r"^(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}[+-]\d\d:\d\d) (DEBUG|INFO|WARNING|ERROR) (.+)$")


def log_lines(text: str) -> list[tuple[str, str, str]]:
    return [m.groups() for m in map(LINE.match, text.splitlines()) if m]


@pytest.fixture(scope="module")
def particles(tmp_path_factory):
    """The bundled particles example dry-run with stdout captured (not a terminal), as
    ``nanoasm dry-run SCENE LAYOUT --report R`` prints it: (stdout, stderr, report)."""
    report = tmp_path_factory.mktemp("particles") / "report.json"
    out, err = dry_run("--report", str(report))
    return out, err, json.loads(report.read_text())


def dry_run(*args: str) -> tuple[str, str]:
    """``nanoasm dry-run`` of the bundled particles example, in this process, its stdout
    and stderr captured (neither a terminal)."""
    import io

    out, err = io.StringIO(), io.StringIO()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(sys, "stdout", out)
        mp.setattr(sys, "stderr", err)
        code = main(["dry-run", str(example("particles_scene.toml")), str(example("particles.toml")), *args])
    assert code == 0, err.getvalue()
    return out.getvalue(), err.getvalue()


def test_a_dry_run_without_a_terminal_logs_every_phase_push_and_scan(particles):
    out, err, report = particles
    lines = log_lines(out)
    messages = [m for _, _, m in lines]
    # the phases in order, each once
    phases = [m.removeprefix("phase: ") for m in messages if m.startswith("phase: ")]
    assert phases == [p for p in PHASES if p in phases] and {"full scan", "identify", "plan", "execute"} <= set(phases)
    # one line per push and per local scan, as the summary and the report count them
    pushes = [m for m in messages if re.match(r"push \d+: ", m)]
    summary = re.search(r"pushes \(failed\)\s*│\s*(\d+) \((\d+)\)", out)
    assert summary is not None, out
    assert len(pushes) == int(summary.group(1)) == report["counts"]["pushes"] > 0
    assert [int(m.split()[1].rstrip(":")) for m in pushes] == list(range(1, len(pushes) + 1))
    scans = [m for m in messages if re.match(r"local scan \d+: ", m)]
    assert len(scans) == report["counts"]["local_scans"] > 0
    assert any(m.startswith("plan: ") for m in messages)            # the run's own events too
    assert messages[-1] == "dry-run done: completed"
    # in time order, and every one of them a whole log line
    assert [t for t, _, _ in lines] == sorted(t for t, _, _ in lines)
    assert all(level == "INFO" for _, level, _ in lines)             # the default level
    # the summary and the report's line as before, after the log lines; stderr as before
    rest = out.splitlines()[len(lines):]
    assert not log_lines("\n".join(rest)) and out.splitlines()[:len(lines)] == [" ".join(x) for x in lines]
    assert "dry-run of sparse-2: 4 of 4 slot(s) filled (the run's check scans)" in rest[0]
    assert rest[-1].endswith("report.json: written")
    assert not log_lines(err)


def test_log_level_warning_leaves_out_the_info_lines():
    out, _ = dry_run("--log-level", "warning")
    assert not [x for x in log_lines(out) if x[1] in ("DEBUG", "INFO")], out
    assert "dry-run of sparse-2: 4 of 4 slot(s) filled" in out


def test_levels_pick_the_lines(capsys):
    """What each level lets through, on a terminal too (``--log-level`` given)."""
    docs = [("event", {"t": 1.0, "level": "info", "text": "plan: 4 slot(s) assigned, 4 push(es)"}),
            ("event", {"t": 2.0, "level": "warn", "text": "o3 moved on its own"}),
            ("checkpoint", {"t": 3.0, "counts": {"pushes": 1}, "remaining": []}),
            ("stop", {"state": "failed", "reason": "OSError: gone"})]
    said = {}
    for name in ("debug", "info", "warning", "error"):
        with progress.run_progress("run", name) as subscribers:
            for topic, doc in docs:
                for follow in subscribers:
                    follow(topic, doc)
        said[name] = [(level, m) for _, level, m in log_lines(capsys.readouterr().out)]
    assert said["debug"] == [("INFO", "plan: 4 slot(s) assigned, 4 push(es)"), ("WARNING", "o3 moved on its own"),
                             ("DEBUG", "checkpoint: 1 push(es) done, 0 to go"), ("ERROR", "run failed: OSError: gone")]
    assert said["info"] == [x for x in said["debug"] if x[0] != "DEBUG"]
    assert said["warning"] == [("WARNING", "o3 moved on its own"), ("ERROR", "run failed: OSError: gone")]
    assert said["error"] == [("ERROR", "run failed: OSError: gone")]


def test_an_unknown_level_is_one_line_before_the_run(capsys):
    code = main(["dry-run", "--log-level", "chatty"])
    out, err = capsys.readouterr()
    assert code == 1 and out == ""
    assert err == "nanoasm: error: --log-level: unknown level 'chatty'; one of debug, info, warning, error\n"


def test_the_bar_names_the_phase_not_what_was_said_before_it(monkeypatch):
    """During planning the bar showed the drift message of the phase before."""
    from rich.console import Console

    bars = []
    real = progress.progress_bar
    monkeypatch.setattr(progress, "progress_bar", lambda console: bars.append(real(console)) or bars[-1])
    monkeypatch.setattr(Console, "is_terminal", property(lambda self: True))
    monkeypatch.setattr(sys.stdout, "isatty", lambda: True, raising=False)
    shown = []
    with progress.run_progress("dry-run") as subscribers:
        task = bars[0].tasks[0]

        def send(topic, doc):
            for follow in subscribers:
                follow(topic, doc)
            shown.append((task.description, task.completed, task.total))

        send("progress", {"step": "phase", "text": "drift"})
        send("event", {"t": 1.0, "level": "info", "text": "drift from the full scan's skew: +0.218, +0.210 nm/s"})
        send("progress", {"step": "phase", "text": "plan"})
        send("plan", {"operations": [{}, {}, {}]})
        send("progress", {"step": "phase", "text": "execute"})
        send("progress", {"step": "push", "text": "o5 towards s4, 377 nm of tip path: pushing"})
        send("checkpoint", {"t": 9.0, "counts": {"pushes": 2}, "remaining": [{}, {}]})
    assert shown == [("dry-run: drift", 0, None),
                     ("dry-run: drift - drift from the full scan's skew: +0.218, +0.210 nm/s", 0, None),
                     ("dry-run: plan", 0, None),
                     ("dry-run: plan", 0, 3),
                     ("dry-run: execute", 0, 3),
                     ("dry-run: execute - push 1: o5 towards s4, 377 nm of tip path: pushing", 1, 3),
                     ("dry-run: execute - push 1: o5 towards s4, 377 nm of tip path: pushing", 2, 4)]


def test_beside_a_bar_on_stderr_the_lines_still_go_to_stdout(monkeypatch, capsys):
    """``nanoasm dry-run > run.txt`` on a terminal: the bar on the terminal, the trail in the file."""
    from rich.console import Console

    monkeypatch.setattr(Console, "is_terminal", property(lambda self: True))
    with progress.run_progress("dry-run") as subscribers:
        for follow in subscribers:
            follow("progress", {"step": "phase", "text": "full scan"})
    out, err = capsys.readouterr()
    assert [m for _, _, m in log_lines(out)] == ["phase: full scan"] and not log_lines(err)


def test_the_lines_are_in_the_file_while_the_run_goes_on(tmp_path):
    """A run with its output redirected to a file leaves a trail as it goes, not at its end."""
    out = tmp_path / "out.txt"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    with open(out, "w") as f:
        proc = subprocess.Popen([sys.executable, "-m", "nanoasm.cli", "dry-run"], cwd=tmp_path, env=env,
                                stdout=f, stderr=subprocess.PIPE, text=True,
                                # a shell may start us with SIGINT ignored, which the child would inherit
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        try:
            deadline = time.monotonic() + 60.0          # the bundled bowtie: half a minute in all
            while "INFO phase: identify" not in out.read_text() and time.monotonic() < deadline:
                assert proc.poll() is None, proc.stderr.read()
                time.sleep(0.05)
            assert proc.poll() is None
            proc.send_signal(signal.SIGINT)
            _, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    assert proc.returncode == 130 and err.strip().splitlines()[-1] == "nanoasm: interrupted", err
    messages = [m for _, _, m in log_lines(out.read_text())]
    assert messages[:1] and "phase: full scan" in messages and "phase: identify" in messages
    assert messages[-1] == "dry-run aborted: interrupted (Ctrl-C)"
