"""Outputs never overwrite inputs, an existing run log needs --force, SIGTERM is one line
and exit 143 (issue 15)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from contextlib import contextmanager

import pytest
from runlogkit import particle_bowtie, stop_when

from nanoasm.cli import main
from nanoasm.examples import path as example

REFUSED = "an output never overwrites an input"


def run(capsys, *args: str) -> tuple[int, str, str]:
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


def one_error_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("nanoasm: error: ") and "Traceback" not in err
    return lines[0]


def snapshot(folder) -> dict[str, bytes]:
    """Every file under ``folder`` with its bytes (links as where they point)."""
    out = {}
    for root, _, files in os.walk(folder):
        for name in files:
            p = os.path.join(root, name)
            out[os.path.relpath(p, folder)] = os.readlink(p) if os.path.islink(p) else open(p, "rb").read()
    return out


@pytest.fixture
def files(tmp_path):
    """The particle bowtie's scene and layout, as TOML and as JSON."""
    scene, layout = particle_bowtie()
    for suffix in (".toml", ".json"):
        scene.save(tmp_path / f"scene{suffix}")
        layout.save(tmp_path / f"layout{suffix}")
    return tmp_path


class _Stop(Exception):
    pass


@pytest.fixture(scope="module")
def stopped(tmp_path_factory):
    """A real stopped dry-run: its log and the world kept beside it, stopped at its second
    checkpoint (the first is logged and kept). Made once, copied by the tests."""
    from nanoasm.dryrun import dry_run_files
    from nanoasm.executor.resume import resume_point
    from nanoasm.harness import LogTo
    from nanoasm.simkeep import sim_state_path

    folder = tmp_path_factory.mktemp("stopped")
    _, layout = particle_bowtie()
    layout.save(folder / "layout.toml")
    log = folder / "run.mcap"
    seen = []

    @contextmanager
    def stop_at_the_second_checkpoint():
        def follow(topic, doc):
            if topic == "checkpoint":
                seen.append(topic)
                if len(seen) == 2:
                    raise _Stop()
        yield [follow]

    with pytest.raises(_Stop):
        dry_run_files(example("bowtie_scene.toml"), folder / "layout.toml", seed=3, log=LogTo(log),
                      progress=stop_at_the_second_checkpoint())
    assert sim_state_path(log).is_file()
    assert resume_point(log, "dry-run").state           # a log a resume goes on from
    return log.read_bytes(), sim_state_path(log).read_bytes()


def _place_stopped(stopped, folder):
    log = folder / "run.mcap"
    log.write_bytes(stopped[0])
    (folder / "run.mcap.sim").write_bytes(stopped[1])
    return log


# -- an output that is an input ---------------------------------------------------------

@pytest.mark.parametrize("spelling", ["same", "dotdot", "symlink"])
def test_plan_refuses_to_write_its_plan_over_its_env(files, capsys, spelling):
    env = files / "env.json"
    env.write_text('{"format": "nanoasm.env/1"}\n')
    out = {"same": env, "dotdot": files / "sub" / ".." / "env.json", "symlink": files / "link.json"}[spelling]
    if spelling == "symlink":
        out.symlink_to(env)
    before = snapshot(files)
    code, stdout, err = run(capsys, "plan", files / "layout.json", "--env", env, "-o", out)
    assert code == 1 and stdout == ""
    assert one_error_line(err) == f"nanoasm: error: {out}: -o: is also an input (--env); {REFUSED}"
    assert snapshot(files) == before


def test_plan_refuses_to_write_its_plan_over_its_layout(files, capsys):
    before = snapshot(files)
    code, _, err = run(capsys, "plan", files / "layout.json", "--env", files / "env.json", "-o", files / "layout.json")
    assert code == 1 and "-o: is also an input (LAYOUT)" in one_error_line(err)
    assert snapshot(files) == before


def test_layout_convert_refuses_to_write_over_its_input(files, capsys):
    before = snapshot(files)
    for target in (files / "layout.toml", files / "." / "layout.toml"):
        code, out, err = run(capsys, "layout", "convert", files / "layout.toml", "-o", target)
        assert code == 1 and out == ""
        assert one_error_line(err) == f"nanoasm: error: {target}: -o: is also an input (FILE); {REFUSED}"
    assert snapshot(files) == before
    # a hard link is the same file too
    os.link(files / "layout.json", files / "hard.json")
    code, _, err = run(capsys, "layout", "convert", files / "layout.json", "-o", files / "hard.json")
    assert code == 1 and "-o: is also an input (FILE)" in one_error_line(err)


@pytest.mark.parametrize("which", ["SCENE", "LAYOUT"])
def test_dry_run_refuses_a_report_over_its_scene_or_layout(files, capsys, which):
    target = files / ("scene.json" if which == "SCENE" else "layout.json")
    before = snapshot(files)
    code, out, err = run(capsys, "dry-run", files / "scene.json", files / "layout.json", "--report", target)
    assert code == 1 and out == ""
    assert one_error_line(err) == f"nanoasm: error: {target}: --report: is also an input ({which}); {REFUSED}"
    assert snapshot(files) == before


@pytest.mark.parametrize("force", [False, True])
def test_dry_run_resume_refuses_to_log_over_the_stopped_log(stopped, tmp_path, capsys, force):
    log = _place_stopped(stopped, tmp_path)
    before = snapshot(tmp_path)
    code, out, err = run(capsys, "dry-run", "--resume", log, "--log", log, *(["--force"] if force else []))
    assert code == 1 and out == ""
    assert one_error_line(err) == f"nanoasm: error: {log}: --log: is also an input (--resume); {REFUSED}"
    assert snapshot(tmp_path) == before              # the stopped log and its kept world as they were
    from nanoasm.executor.resume import resume_point

    assert resume_point(log, "dry-run").state


def test_dry_run_resume_refuses_to_log_onto_the_kept_world(stopped, tmp_path, capsys):
    log = _place_stopped(stopped, tmp_path)
    before = snapshot(tmp_path)
    code, _, err = run(capsys, "dry-run", "--resume", log, "--log", tmp_path / "run.mcap.sim", "--force")
    assert code == 1 and "--log: is also an input (the world kept for --resume)" in one_error_line(err)
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("args,fragment", [
    (["run", "--instrument", "{d}/instrument.toml", "--resume", "{d}/run.mcap", "--log", "{d}/run.mcap"],
     "{d}/run.mcap: --log: is also an input (--resume)"),
    (["run", "{d}/layout.json", "--instrument", "{d}/instrument.toml", "--report", "{d}/layout.json"],
     "{d}/layout.json: --report: is also an input (LAYOUT)"),
    (["identify", "{d}/scan.json", "-o", "{d}/scan.json"], "{d}/scan.json: -o: is also an input (SCAN)"),
    (["review", "{d}/run.png", "--plot", "{d}/run.png"], "{d}/run.png: --plot: is also an input (LOG)"),
    (["plan", "{d}/layout.json", "--scan", "{d}/scan.json", "-o", "{d}/scan.json"],
     "{d}/scan.json: -o: is also an input (--scan)"),
])
def test_other_commands_refuse_an_output_over_an_input(files, capsys, args, fragment):
    from shutil import copyfile

    copyfile(example("instrument_ni.toml"), files / "instrument.toml")
    for name in ("run.mcap", "scan.json", "run.png"):
        (files / name).write_bytes(b"an input\n")
    before = snapshot(files)
    code, _, err = run(capsys, *(a.format(d=files) for a in args))
    assert code == 1
    assert one_error_line(err) == f"nanoasm: error: {fragment.format(d=files)}; {REFUSED}"
    assert snapshot(files) == before


# -- an existing log needs --force -------------------------------------------------------

@pytest.mark.parametrize("existing", ["run.mcap", "run.mcap.sim"])
def test_dry_run_refuses_an_existing_log_without_force(files, capsys, existing):
    (files / existing).write_bytes(b"an earlier run's\n")
    before = snapshot(files)
    code, out, err = run(capsys, "dry-run", files / "scene.toml", files / "layout.toml", "--log", files / "run.mcap",
                         "--report", files / "r.json")
    assert code == 1 and out == ""
    line = one_error_line(err)
    assert line.startswith(f"nanoasm: error: {files / existing}: --log: ") and "give --force" in line
    assert snapshot(files) == before                # no log, no kept world, no report
    # checked before any work: before the scene is even read
    code, _, err = run(capsys, "dry-run", files / "none.toml", files / "layout.toml", "--log", files / "run.mcap")
    assert code == 1 and "give --force" in one_error_line(err)


def test_run_refuses_an_existing_log_without_force(files, capsys):
    (files / "run.mcap").write_bytes(b"an earlier run's\n")
    before = snapshot(files)
    code, _, err = run(capsys, "run", files / "layout.toml", "--instrument", example("instrument_ni.toml"),
                       "--log", files / "run.mcap")
    assert code == 1
    assert one_error_line(err) == f"nanoasm: error: {files / 'run.mcap'}: --log: exists; give --force to overwrite it"
    assert snapshot(files) == before


def test_dry_run_overwrites_an_existing_log_with_force(files, capsys):
    from nanoasm.executor.logread import read_log
    from nanoasm.simkeep import read_sim_state

    log = files / "run.mcap"
    log.write_bytes(b"an earlier run's\n")
    (files / "run.mcap.sim").write_bytes(b"an earlier world\n")
    code, _, err = run(capsys, "dry-run", files / "scene.toml", files / "layout.toml", "--seed", "3",
                       "--log", log, "--force")
    assert code == 0, err
    assert read_log(log).complete and read_log(log).topic("/result")
    assert read_sim_state(files / "run.mcap.sim")["t"] > 0      # the new run's world, not the old bytes


# -- SIGTERM ------------------------------------------------------------------------------

def test_sigterm_stops_a_dry_run_with_exit_143_and_one_line(files):
    from nanoasm.executor.logread import read_log

    log = files / "t.mcap"
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "NANOASM_DEBUG")}
    proc = subprocess.Popen([sys.executable, "-m", "nanoasm.cli", "dry-run", str(example("bowtie_scene.toml")),
                             str(example("bowtie.toml")), "--seed", "3", "--log", str(log)],
                            cwd=files, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    err = stop_when(proc, log.exists, [(0.5, signal.SIGTERM)], 60.0)     # 0.5 s into the run
    assert proc.returncode == 143, err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert lines[-1] == "nanoasm: terminated", err
    assert lines[:-1] == [f"{log}: written"], err   # the log closed as before, nothing else said
    contents = read_log(log)
    assert contents.complete                         # closed properly, footer and all
    assert [m.data["reason"] for m in contents.topic("/stop")] == ["terminated (SIGTERM)"]


@pytest.mark.parametrize("stop, reason", [("sigterm", "terminated (SIGTERM)"),
                                          ("ctrl-c", "interrupted (Ctrl-C)")])
def test_a_log_stopped_before_its_run_began_says_so(tmp_path, stop, reason, capsys):
    """A signal between the log's opening and the run's start (the simulated lever's
    calibration, the plan: seconds on a loaded machine) closes the log with the /stop
    the engine would have written; the SIGTERM test above hit that window at 0.5 s."""
    from nanoasm import cli
    from nanoasm.executor.logread import read_log
    from nanoasm.harness import LogTo, run_logs

    _, layout = particle_bowtie()
    signals = {"sigterm": cli._Terminated, "ctrl-c": KeyboardInterrupt}
    path = tmp_path / "early.mcap"
    with pytest.raises(signals[stop]):
        with run_logs(LogTo(path), layout, {"kind": "dry-run"}):
            raise signals[stop]()
    contents = read_log(path)
    assert contents.complete
    assert [m.data for m in contents.topic("/stop")] == [{"state": "aborted", "reason": reason}]
    with pytest.raises(ValueError):             # any other error: the log closes without a word of its own
        with run_logs(LogTo(tmp_path / "err.mcap"), layout, {"kind": "dry-run"}):
            raise ValueError("x")
    assert not read_log(tmp_path / "err.mcap").topic("/stop")


def test_sigterm_outside_a_run_is_the_same_line(monkeypatch, capsys):
    """SIGTERM before the run engine runs (here: while a layout is read) is one line too."""
    from nanoasm import cli

    def terminated(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5.0)                             # the handler raises before this ends
        raise AssertionError("SIGTERM was not handled")

    monkeypatch.setattr(cli, "_read_layout", terminated)
    previous = signal.getsignal(signal.SIGTERM)
    code, out, err = run(capsys, "layout", "check", example("bowtie.toml"))
    assert code == 143 and out == "" and err == "nanoasm: terminated\n"
    assert signal.getsignal(signal.SIGTERM) == previous        # restored after the command


def test_an_output_into_a_missing_folder_is_refused_before_the_run(tmp_path, capsys):
    """dry-run --report into a folder that does not exist was found out only after the
    run, losing it: now one line at the start, exit 1, nothing run."""
    import time

    from nanoasm.cli import main

    t0 = time.perf_counter()
    code = main(["dry-run", "--report", str(tmp_path / "nowhere" / "r.json")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1 and "--report" in err[0] and "does not exist" in err[0]
    assert time.perf_counter() - t0 < 5.0                 # the bundled dry-run takes longer
    assert main(["scene", "random", "-o", str(tmp_path / "nowhere" / "s.toml")]) == 1
    assert "does not exist" in capsys.readouterr().err


def test_a_full_disk_is_one_line_and_leaves_no_file(tmp_path, monkeypatch):
    import errno
    import os

    import pytest

    from nanoasm.errors import InputError
    from nanoasm.fileio import write_atomic

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "replace", full)
    with pytest.raises(InputError, match="cannot write: No space left on device"):
        write_atomic(tmp_path / "out.json", "{}")
    assert list(tmp_path.iterdir()) == []
