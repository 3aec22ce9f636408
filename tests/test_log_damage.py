"""A damaged chunk in the middle of a run log (issue 15, item 5): read past, reviewed past,
resumed from the last checkpoint that reads, and told in one line naming the bytes lost."""

from __future__ import annotations

import shutil
import subprocess
import sys

import pytest
from runlogkit import chunk_topics, cli_env, killed_after, particle_bowtie

from nanoasm.cli import main
from nanoasm.dryrun import dry_run
from nanoasm.examples import path as example
from nanoasm.executor.logread import read_log
from nanoasm.executor.report import load_report
from nanoasm.executor.strategy import ExecOptions
from nanoasm.planner import PlanOptions
from nanoasm.review import review
from nanoasm.simkeep import sim_state_path


@pytest.fixture(scope="module")
def stopped(tmp_path_factory):
    """A dry-run killed after its world was kept a third time (its log and kept world), and the
    chunks of its log."""
    folder = tmp_path_factory.mktemp("damage")
    _, layout = particle_bowtie()
    layout.save(folder / "particles.toml")
    log = folder / "run.mcap"
    killed_after(["dry-run", example("bowtie_scene.toml"), "particles.toml", "--seed", "3", "--log", log], 3, folder)
    return log, chunk_topics(log)


def _damaged(stopped, tmp_path, which: str, index: int, how: str = "data"):
    """A copy of the stopped log (and its world) with the ``index``-th chunk holding
    ``which`` damaged: 32 bytes of its data zeroed, or (``how="length"``) its record's
    length garbled. Returns the copy and the chunk's (start, end) bytes."""
    log, chunks = stopped
    start, end, _ = [c for c in chunks if which in c[2]][index]
    data = bytearray(log.read_bytes())
    if how == "length":
        data[start + 1:start + 9] = b"\xff" * 8
    else:
        mid = (start + end) // 2
        data[mid:mid + 32] = bytes(32)
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    shutil.copy(sim_state_path(log), sim_state_path(bad))
    return bad, (start, end)


def _tip_paths(log) -> list:
    return [[tuple(p) for p in m.data["op"]["tip_path"]] for m in read_log(log, topics={"/push"}).topic("/push")]


@pytest.mark.parametrize("how", ["data", "length"])
def test_a_damaged_chunk_is_skipped_and_the_rest_read(stopped, tmp_path, how):
    bad, (start, end) = _damaged(stopped, tmp_path, "/push", 1, how)
    whole, log = read_log(stopped[0]), read_log(bad)
    assert len(log.damage) == 1 and not log.complete
    d = log.damage[0]
    assert d.start == start and (d.end == end if how == "data" else d.end > end)
    assert d.after < d.before                     # the times between which the part was logged
    pushes = whole.topic("/push")
    kept = [m.t for m in log.topic("/push")]
    assert kept == [pushes[0].t] + [m.t for m in pushes[2:]]          # read on to the end
    assert d.after < pushes[1].t <= d.before
    assert len(log.topic("/checkpoint")) == len(whole.topic("/checkpoint"))
    assert log.warnings() == [f"{bad}: {d.line()}"] and f"bytes {start}-" in d.line()


def test_review_shows_every_intact_push_and_the_span_lost(stopped, tmp_path, capsys):
    bad, (start, end) = _damaged(stopped, tmp_path, "/push", 1)
    rev = review(bad)
    paths = _tip_paths(stopped[0])
    assert [p for p, _ in rev.paths] == paths[:1] + paths[2:]       # beyond the damaged chunk too
    assert len(rev.damage) == 1 and rev.damage[0].startswith(f"bytes {start}-{end} unreadable")
    assert main(["review", str(bad)]) == 0
    out, err = capsys.readouterr()
    assert "damaged" in out and "is lost" in " ".join(out.split())
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"nanoasm: warning: {bad}: bytes {start}-{end} unreadable")
    assert "between t = " in lines[0]


def _resume(bad, tmp_path):
    report = tmp_path / "r.json"
    done = subprocess.run([sys.executable, "-m", "nanoasm.cli", "dry-run", "--resume", str(bad), "--report",
                           str(report)], cwd=tmp_path, capture_output=True, text=True, timeout=300, env=cli_env())
    assert done.returncode == 0, done.stderr
    warnings = [ln for ln in done.stderr.splitlines() if ln.startswith("nanoasm: warning: ")]
    return load_report(report), warnings


def test_a_damaged_log_is_resumed_and_ends_as_the_uninterrupted_run(stopped, tmp_path):
    scene, layout = particle_bowtie()
    whole = dry_run(scene, layout, seed=3, options=ExecOptions(), plan_options=PlanOptions(seed=3))
    bad, (start, end) = _damaged(stopped, tmp_path, "/push", 1)
    rep, warnings = _resume(bad, tmp_path)
    assert len(warnings) == 1 and f"{bad}: bytes {start}-{end} unreadable" in warnings[0]
    assert rep.counts == whole.report.counts and rep.assignment == whole.report.assignment
    assert {o.id: o.at for o in rep.final_objects} == {o.id: o.at for o in whole.report.final_objects}


def test_a_lost_last_checkpoint_goes_on_from_the_one_before_with_the_world_as_it_is(stopped, tmp_path):
    """The kept world stands at the last checkpoint, which the damage took: the run goes
    on from the one before, as a real run would, not knowing of the push between (it
    scans each object before pushing it), and says so."""
    bad, _ = _damaged(stopped, tmp_path, "/checkpoint", -1)
    ckpts = read_log(bad, topics={"/checkpoint"}).topic("/checkpoint")
    rep, warnings = _resume(bad, tmp_path)
    assert len(warnings) == 2 and "was lost in the damage" in warnings[1]
    assert f"going on from the one at t = {ckpts[-1].t:.3f} s" in warnings[1]
    resumed = read_log(tmp_path / "bad-resumed.mcap")
    assert resumed.complete and resumed.topic("/checkpoint")[0].t == pytest.approx(ckpts[-1].t, abs=1e-6)
    assert len(rep.assignment) == len(rep.targets)
