"""A resumed dry-run killed in turn is resumed from its own log (issue 15, item 4), and a
resumed run's report counts the stopped run's wall time with its parts."""

from __future__ import annotations

import subprocess
import sys

import pytest
from runlogkit import cli_env, killed_after, particle_bowtie

from nanoasm.dryrun import dry_run, filled_slots
from nanoasm.examples import path as example
from nanoasm.executor.logread import read_log
from nanoasm.executor.report import load_report
from nanoasm.executor.strategy import ExecOptions
from nanoasm.planner import PlanOptions
from nanoasm.simkeep import read_sim_state, sim_state_path


@pytest.fixture(scope="module")
def whole():
    scene, layout = particle_bowtie()
    return layout, dry_run(scene, layout, seed=3, options=ExecOptions(), plan_options=PlanOptions(seed=3))


def _wall_adds_up(report) -> None:
    w = report.wall_time
    parts = w.identify + w.plan + w.execute
    # the total is the parts and what lies outside them (the check scans, the harness): a little more
    assert parts <= w.total + 1e-6 and w.total - parts < max(0.5, 0.25 * w.total), w


def test_a_resumed_dry_run_killed_in_turn_is_resumed_from_its_own_log(tmp_path, whole):
    layout, run = whole
    layout.save(tmp_path / "particles.toml")
    a, b, c = (tmp_path / f"{k}.mcap" for k in "abc")
    killed_after(["dry-run", example("bowtie_scene.toml"), "particles.toml", "--seed", "3", "--log", a], 2, tmp_path)
    # the resumed run keeps its world at its start and after each of its own pushes: killed after two
    killed_after(["dry-run", "--resume", a, "--log", b], 3, tmp_path)
    stopped = read_log(b)
    assert not stopped.complete and not stopped.topic("/result")
    for topic in ("/environment", "/plan", "/checkpoint"):       # carried over from a, then its own
        assert stopped.topic(topic), topic
    assert "full_scan.npz" in stopped.attachments and "plan.json" in stopped.attachments
    assert len(stopped.topic("/checkpoint")) == 3
    assert read_sim_state(sim_state_path(b))["t"] == pytest.approx(stopped.topic("/checkpoint")[-1].t, abs=1e-6)

    report = tmp_path / "c.json"
    done = subprocess.run([sys.executable, "-m", "nanoasm.cli", "dry-run", "--resume", str(b), "--log", str(c),
                           "--report", str(report)], cwd=tmp_path, capture_output=True, text=True, timeout=300,
                          env=cli_env())
    assert done.returncode == 0, done.stderr
    rep = load_report(report)
    assert rep.counts == run.report.counts and rep.assignment == run.report.assignment
    assert rep.pushed == run.report.pushed and rep.slots == run.report.slots
    final = {o.id: o.at for o in rep.final_objects}
    assert final == {o.id: o.at for o in run.report.final_objects}       # bit for bit, every object
    assert set(filled_slots(layout, rep.assignment, {o.id: o for o in rep.final_objects})[0]) == set(run.filled)
    assert read_log(c).complete
    assert read_log(c).metadata["nanoasm"]["resumed_from"] == str(b)
    _wall_adds_up(rep)


def test_a_resumed_reports_wall_time_adds_up(tmp_path):
    """The stopped run's compute (its full scan and identification above all) is in the
    resumed report's stages: the total counts it too (it was the resumed process's alone,
    44.8 s beside parts adding up to 83.8 s)."""
    scene, layout = particle_bowtie()
    layout.save(tmp_path / "particles.toml")
    a = tmp_path / "a.mcap"
    killed_after(["dry-run", example("bowtie_scene.toml"), "particles.toml", "--seed", "3", "--log", a], 3, tmp_path)
    report = tmp_path / "r.json"
    done = subprocess.run([sys.executable, "-m", "nanoasm.cli", "dry-run", "--resume", str(a), "--report",
                           str(report)], cwd=tmp_path, capture_output=True, text=True, timeout=300, env=cli_env())
    assert done.returncode == 0, done.stderr
    rep = load_report(report)
    assert rep.wall_time.identify > 0.0         # the stopped run's, carried in its checkpoint
    _wall_adds_up(rep)
