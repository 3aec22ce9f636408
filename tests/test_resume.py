"""Resuming stopped runs: from a checkpoint in memory, through the executor's state in the
log, and a dry-run killed with SIGKILL and resumed from the command line."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest
from runlogkit import kill_when, particle_bowtie

from nanoasm.dryrun import dry_run
from nanoasm.errors import InputError
from nanoasm.examples import path as example
from nanoasm.executor.assembly import Assembly
from nanoasm.executor.engine import RunEngine
from nanoasm.executor.logread import read_log
from nanoasm.executor.report import load_report
from nanoasm.executor.resume import ShiftedClock, clock_shift, resume_point, resumed_log_path
from nanoasm.executor.strategy import ExecOptions
from nanoasm.simkeep import load_sim_state, sim_state_path
from nanoasm.world.sim import SimulatedAFM


def _final(sim: SimulatedAFM) -> dict[str, tuple[float, float]]:
    return {b.id: b.at for b in sim.truth()}


def _run_and_keep(k: int, strategy: str = "full", seed: int = 3, trust: float = 0.0):
    """An uninterrupted run that keeps the world and the state at its k-th checkpoint."""
    scene, layout = particle_bowtie()
    sim = SimulatedAFM(scene, seed=seed)
    kept: dict = {"scene": scene}

    def keep(topic: str, doc: dict) -> None:
        # what resume_point takes from a log: a checkpoint, the environment and the first plan
        if topic in ("environment", "plan") and topic not in kept:
            kept[topic] = json.loads(json.dumps(doc))
        if topic == "checkpoint":
            kept["n"] = kept.get("n", 0) + 1
            if kept["n"] == k:
                kept["state"] = {**json.loads(json.dumps(doc)), "env": kept["environment"],
                                 "first_plan": kept["plan"]}
                kept["sim"] = json.dumps(sim.state_dict(), allow_nan=False)   # as the dry-run keeps it

    options = ExecOptions(strategy=strategy, trust_after_scan=trust)
    summary = RunEngine(sim, [keep]).run(Assembly(layout, options).procedure(sim.config))
    return layout, sim, summary, kept


@pytest.mark.parametrize("strategy,trust", [("full", 0.0), ("kalman", 0.0), ("full", 60.0)])
def test_a_run_resumed_from_a_checkpoint_ends_as_the_uninterrupted_run(strategy, trust):
    # trust_after_scan: the last after-scan a push may start from is kept in checkpoints
    layout, sim, summary, kept = _run_and_keep(3, strategy, trust=trust)
    assert "state" in kept, "the run ended before its third push"
    sim2 = SimulatedAFM.from_state(kept["scene"], json.loads(kept["sim"]))
    resumed = RunEngine(sim2, []).run(Assembly(layout, ExecOptions(strategy=strategy, trust_after_scan=trust))
                                      .resume(sim2.config, kept["state"]))
    assert resumed.counts == summary.counts
    assert resumed.assignment == summary.assignment and resumed.unfilled == summary.unfilled
    assert resumed.pushed == summary.pushed
    a, b = _final(sim), _final(sim2)
    assert max(np.hypot(*np.subtract(a[i], b[i])) for i in a) < 1e-6
    assert a == b and sim.ledger() == sim2.ledger()              # bit for bit, the whole world
    assert json.dumps(sim.state_dict()) == json.dumps(sim2.state_dict())


def test_a_run_resumed_after_its_check_scans_reports_them_without_scanning_again():
    # the last checkpoint follows the check scans; resumed from it, the run scanned every
    # slot again and counted those scans twice (39 local scans where the run made 33)
    n = _run_and_keep(10_000)[3]["n"]
    layout, sim, summary, kept = _run_and_keep(n)
    assert kept["state"]["remaining"] == [] and kept["state"]["checked"]
    sim2 = SimulatedAFM.from_state(kept["scene"], json.loads(kept["sim"]))
    events: list[str] = []
    resumed = RunEngine(sim2, [lambda t, d: events.append(d.text) if t == "event" else None]).run(
        Assembly(layout, ExecOptions()).resume(sim2.config, kept["state"]))
    assert resumed.counts == summary.counts and resumed.slots == summary.slots
    assert resumed.assignment == summary.assignment
    assert sim2.ledger() == sim.ledger()                          # nothing scanned, nothing moved
    assert any("after the check scans" in e for e in events) and not any("check scans of" in e for e in events)


def test_a_resume_after_a_pause_widens_the_search_and_still_finishes():
    """The instrument's clock restarted (a new process) and ten minutes passed: the
    shifted clock goes on, the filter's uncertainty has grown, the run ends normally."""
    layout, sim, summary, kept = _run_and_keep(2)
    sim2 = SimulatedAFM.from_state(kept["scene"], json.loads(kept["sim"]))
    sim2._clock.advance(600.0, "travel")          # the sample drifted on while nothing ran
    restarted = ShiftedClock(sim2, -sim2.clock())  # a new process: its clock starts at 0
    assert restarted.clock() == 0.0
    state = {**kept["state"], "saved_at": time.time() - 600.0}
    shifted = ShiftedClock(restarted, clock_shift(state, restarted.clock()))
    assert shifted.clock() == pytest.approx(kept["state"]["t"] + 600.0, abs=1.0)
    events: list[str] = []
    resumed = RunEngine(shifted, [lambda t, d: events.append(d.text) if t == "event" else None]).run(
        Assembly(layout, ExecOptions()).resume(shifted.config, state))
    assert any("resumed from the checkpoint after push" in e for e in events)
    assert len(resumed.assignment) == len(summary.assignment)
    # it goes on from the checkpoint's pushes (the paused run may need more or fewer
    # corrections than the uninterrupted one) and fills the slots its verdict names
    assert resumed.counts.pushes > kept["state"]["counts"]["pushes"]
    assert [v.target for v in resumed.slots if v.state == "filled"] == [
        v.target for v in summary.slots if v.state == "filled"]


def test_a_checkpoint_of_another_strategy_or_format_is_refused():
    layout, _, _, kept = _run_and_keep(1)
    with pytest.raises(ValueError, match="strategy"):
        next(Assembly(layout, ExecOptions(strategy="kalman")).resume(None, kept["state"]))
    with pytest.raises(ValueError, match="checkpoint"):
        next(Assembly(layout, ExecOptions()).resume(None, {**kept["state"], "format": "x"}))


def _dry_run_cli(args, cwd, **kw):
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return subprocess.Popen([sys.executable, "-m", "nanoasm.cli", *args], cwd=cwd, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, **kw)


def test_a_killed_dry_run_resumed_fills_the_slots_the_uninterrupted_run_fills(tmp_path):
    # run with --contact-batch 1 (not the default): the resumed run must keep its log's
    scene, layout = particle_bowtie()
    layout_file = tmp_path / "particles.toml"
    layout.save(layout_file)
    scene_file = example("bowtie_scene.toml")
    whole = dry_run(scene, layout, seed=3, options=ExecOptions(contact_batch=1))

    log = tmp_path / "run.mcap"
    proc = _dry_run_cli(["dry-run", str(scene_file), str(layout_file), "--seed", "3", "--log", str(log),
                         "--contact-batch", "1"], tmp_path)
    kill_when(proc, lambda: log.exists() and len(read_log(log, topics={"/checkpoint"}).topic("/checkpoint")) >= 2)
    kept = sim_state_path(log)
    assert kept.exists() and kept.stat().st_mode & 0o777 == 0o600
    good = kept.read_bytes()
    doc = json.loads(good)                      # JSON, not a pickle
    assert doc["format"] == "nanoasm.simstate/2" and doc["world"]["format"] == "nanoasm.simworld/1"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    for key, value, text in (("scene_sha256", "0" * 64, "scene_sha256: the world kept is of another scene"),
                             ("seed", -1, "seed: must be a non-negative integer")):
        kept.write_text(json.dumps({**doc, "world": {**doc["world"], key: value}}))
        done = subprocess.run([sys.executable, "-m", "nanoasm.cli", "dry-run", "--resume", str(log)], cwd=tmp_path,
                              capture_output=True, text=True, timeout=120, env=env)
        lines = done.stderr.strip().splitlines()
        assert done.returncode == 1 and len(lines) == 1, done.stderr
        assert lines[0].startswith(f"nanoasm: error: {kept}: world: ") and text in lines[0], lines[0]
    kept.write_bytes(good)
    report = tmp_path / "resumed.json"
    done = subprocess.run([sys.executable, "-m", "nanoasm.cli", "dry-run", "--resume", str(log),
                           "--report", str(report)], cwd=tmp_path, capture_output=True, text=True, timeout=300,
                          env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"})
    assert done.returncode == 0, done.stderr
    rep = load_report(report)
    final = {b.id: b for b in rep.final_objects}
    from nanoasm.dryrun import filled_slots

    filled, errors = filled_slots(layout, rep.assignment, final)
    assert set(filled) == set(whole.filled)
    assert rep.counts == whole.report.counts
    assert rep.instrument_time.mode_switch == pytest.approx(whole.report.instrument_time.mode_switch, abs=1.0)
    for t, e in errors.items():
        assert e == pytest.approx(whole.errors[t], abs=0.5)
    # the resumed run wrote its own log beside the first, which stays as it was
    resumed_log = tmp_path / "run-resumed.mcap"
    assert resumed_log.exists() and read_log(resumed_log).complete and not read_log(log).complete
    from nanoasm.review import review

    assert review(resumed_log).metadata.get("resumed_from") == str(log)
    assert resumed_log_path(log) == tmp_path / "run-resumed2.mcap"


def test_resume_refuses_what_it_cannot_resume(tmp_path):
    with pytest.raises(InputError, match="no such run log"):
        resume_point(tmp_path / "missing.mcap", "dry-run")
    finished = tmp_path / "done.mcap"
    from runlogkit import logged_dry_run

    logged_dry_run(finished)
    with pytest.raises(InputError, match="nothing to resume"):
        resume_point(finished, "dry-run")
    with pytest.raises(InputError, match="not a run's log .resume it with nanoasm dry-run --resume"):
        resume_point(finished, "run")
    with pytest.raises(InputError, match="missing"):
        load_sim_state(tmp_path / "none.mcap.sim", None)
    bad = tmp_path / "bad.sim"
    bad.write_bytes(b"not a pickle")
    with pytest.raises(InputError, match="unreadable"):
        load_sim_state(bad, None)


def test_resume_errors_on_the_command_line_are_one_line(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    for args, text in ((["dry-run", "--resume", "nope.mcap"], "no such run log"),
                       (["dry-run", str(example("bowtie_scene.toml")), str(example("bowtie.toml")),
                         "--resume", "x.mcap"], "give neither"),
                       (["run", "--instrument", str(example("instrument_ni.toml")), "--resume", "nope.mcap"],
                        "no such run log"),
                       (["dry-run", "--resume", "x.mcap", "--report", "r.txt"], "report must end in .json")):
        if "give neither" in text:
            (tmp_path / "x.mcap").write_bytes(b"")
        done = subprocess.run([sys.executable, "-m", "nanoasm.cli", *args], cwd=tmp_path, capture_output=True,
                              text=True, timeout=120, env=env)
        assert done.returncode == 1, done.stderr
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and text in lines[0], done.stderr
