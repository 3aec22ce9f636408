"""``nanoasm review``: the table and plot of a run log, truncated logs, bad files; and the
``--log`` option of ``nanoasm dry-run``."""

from __future__ import annotations

import math

import pytest
from runlogkit import logged_dry_run, particle_bowtie

from nanoasm.cli import main
from nanoasm.executor.assembly import Assembly
from nanoasm.executor.engine import RunEngine
from nanoasm.executor.runlog import RunLog
from nanoasm.executor.strategy import ExecOptions
from nanoasm.review import review
from nanoasm.world.sim import SimulatedAFM


@pytest.fixture(scope="module")
def logged(tmp_path_factory):
    path = tmp_path_factory.mktemp("review") / "run.mcap"
    out, _ = logged_dry_run(path, seed=4, strategy="kalman")
    return path, out


@pytest.fixture(scope="module")
def belief_log(tmp_path_factory):
    """A log as a real run writes it: the engine and a RunLog, no harness, no truth."""
    scene, layout = particle_bowtie()
    path = tmp_path_factory.mktemp("review") / "real.mcap"
    sim = SimulatedAFM(scene, seed=2)
    assembly = Assembly(layout, ExecOptions(strategy="anchor"))
    summary = RunEngine(sim, [RunLog(path, layout=layout, metadata={"kind": "run"})]).run(
        assembly.procedure(sim.config))
    return path, summary, layout


def test_review_matches_the_dry_run(logged):
    path, out = logged
    rev = review(path)
    assert rev.complete and rev.kind == "dry-run" and rev.source == "simulated truth"
    assert rev.filled == len(out.filled)
    errors = {s.target: s.error for s in rev.slots}
    assert errors == pytest.approx(out.errors)
    assert rev.pushes == out.report.counts.pushes
    assert rev.failed_pushes == out.report.counts.failed_pushes
    assert len(rev.failures) == len(out.summary.failures)
    t = out.report.instrument_time
    assert rev.times == pytest.approx({"full_scan": t.full_scan, "local_scan": t.local_scan, "push": t.push,
                                       "travel": t.travel})
    assert rev.total_time == pytest.approx(t.total, abs=1.0)
    assert rev.drift and rev.drift[-1][3] > 0          # the kalman filter's sigma


def test_a_real_run_is_reviewed_against_its_last_belief(belief_log):
    path, summary, layout = belief_log
    rev = review(path)
    assert rev.complete and rev.kind == "run" and rev.source == "belief"
    final = {oid: o for oid, o in summary.belief.objects.items() if oid not in summary.belief.lost}
    assert {b.id: b.at for b in rev.final} == {oid: o.at for oid, o in final.items()}
    assert rev.slots
    for s in rev.slots:
        assert s.error == pytest.approx(math.dist(layout.target(s.target).at, final[s.object].at))
    assert rev.drift and all(r[3] != r[3] for r in rev.drift)    # the anchor gives no sigma (NaN)


def test_cli_review_prints_the_table_and_plots(logged, tmp_path, capsys):
    path, out = logged
    png = tmp_path / "review.png"
    assert main(["review", str(path), "--plot", str(png)]) == 0
    text = capsys.readouterr().out
    assert f"{len(out.filled)} of 6 slot(s) filled" in text
    for row in ("slot l1", "pushes (failed)", "instrument time", "drift estimate", "simulated truth"):
        assert row in text
    assert "incomplete" not in text
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(tmp_path.glob(".*.tmp"))


def test_cli_review_of_a_truncated_log_says_so(logged, tmp_path, capsys):
    path, _ = logged
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    assert main(["review", str(cut), "--plot", str(tmp_path / "cut.svg")]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "incomplete: log ends at t =" in text and "push(es)" in text
    assert (tmp_path / "cut.svg").exists()


@pytest.mark.parametrize("content, message", [
    (None, "no such file"),
    (b"", "empty"),
    (b"format = 'nanoasm.layout/1'\n", "not an MCAP run log"),
])
def test_cli_review_of_a_bad_file_is_one_line(tmp_path, capsys, content, message):
    bad = tmp_path / "bad.mcap"
    if content is not None:
        bad.write_bytes(content)
    assert main(["review", str(bad)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and str(bad) in err and message in err


def test_cli_review_refuses_a_bad_plot_name(logged, tmp_path, capsys):
    assert main(["review", str(logged[0]), "--plot", str(tmp_path / "p.txt")]) == 1
    assert "plot must end in .png, .svg or .pdf" in capsys.readouterr().err


def test_dry_run_with_a_bad_log_name_writes_nothing(tmp_path, capsys):
    scene, layout = particle_bowtie()
    layout.save(tmp_path / "l.toml")
    scene.save(tmp_path / "s.toml")
    bad = tmp_path / "run.log"
    assert main(["dry-run", str(tmp_path / "s.toml"), str(tmp_path / "l.toml"), "--log", str(bad)]) == 1
    assert "run log must end in .mcap" in capsys.readouterr().err
    assert not bad.exists()


def test_a_malformed_message_is_skipped_with_a_note(logged, tmp_path, capsys):
    """A push without its belief: review leaves it out and says so; read strictly, it is
    one error naming the file, the channel and the key."""
    from nanoasm.errors import InputError
    from nanoasm.executor.documents import PUSH
    from nanoasm.executor.logread import read_log

    pushes = [m.data for m in read_log(logged[0]).topic("/push")]
    bad = tmp_path / "bad.mcap"
    log = RunLog(bad, metadata={"kind": "run"})
    log(PUSH, pushes[0])
    log(PUSH, {k: v for k, v in pushes[1].items() if k != "belief"})
    log.close()
    rev = review(bad)
    assert rev.complete and len(rev.paths) == 1 and rev.pushes == 1
    assert len(rev.notes) == 1 and "/push at t =" in rev.notes[0] and "push document: belief: missing" in rev.notes[0]
    assert main(["review", str(bad)]) == 0
    assert "skipped" in capsys.readouterr().out
    with pytest.raises(InputError, match=r"bad.mcap: /push: at t = .*: push document: belief: missing required key"):
        read_log(bad).documents(PUSH)
