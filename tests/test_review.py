"""``nanoasm review``: the table and plot of a run log, truncated logs, bad files; and the
``--log`` option of ``nanoasm dry-run``."""

from __future__ import annotations

import io
import math
import re
import xml.etree.ElementTree as ET

import pytest
from runlogkit import logged_dry_run, particle_bowtie

from nanoasm.cad.layout import layout_from_dict
from nanoasm.cli import main
from nanoasm.dryrun import dry_run
from nanoasm.executor.assembly import Assembly
from nanoasm.executor.engine import RunEngine
from nanoasm.executor.logread import read_log
from nanoasm.executor.runlog import RunLog
from nanoasm.executor.strategy import ExecOptions
from nanoasm.review import plot_review, print_review, review
from nanoasm.review_plot import review_figure
from nanoasm.world.scene import scene_from_dict
from nanoasm.world.sim import SimulatedAFM

#: A rod and two particles, named ``o1``-``o3`` in an order other than the one the run
#: identifies them in: the scene's ``o2`` (the rod) is not the run's ``o2``.
ROD_SCENE = {"format": "nanoasm.scene/1", "area": [2000, 2000], "seed": 5,
             "drift": {"velocity": [0.2, 0.15], "random_walk": 0.1},
             "object": [{"id": "o1", "kind": "particle", "at": [1500, 1500], "diameter": 90},
                        {"id": "o2", "kind": "rod", "at": [1000, 700], "angle": 20, "length": 500, "diameter": 70},
                        {"id": "o3", "kind": "particle", "at": [400, 1300], "diameter": 90}]}
#: A rod slot and a particle slot.
ROD_LAYOUT = {"format": "nanoasm.layout/1", "name": "rod-and-particle", "area": [2000, 2000],
              "target": [{"id": "bar", "kind": "rod", "at": [1000, 1000], "angle": 0, "length": 500, "diameter": 70},
                         {"id": "s1", "kind": "particle", "at": [1450, 1300], "diameter": 90}]}


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


@pytest.fixture(scope="module")
def rod_log(tmp_path_factory):
    """A dry-run of one rod slot and one particle slot (a few seconds), logged."""
    scene, layout = scene_from_dict(ROD_SCENE), layout_from_dict(ROD_LAYOUT)
    path = tmp_path_factory.mktemp("review") / "rod.mcap"
    log = RunLog(path, layout=layout, metadata={"kind": "dry-run", "seed": 5}, truth=True)
    try:
        out = dry_run(scene, layout, seed=5, subscribers=[log])
    finally:
        log.close()
    return path, out


def svg_texts(path) -> dict[str, str]:
    """The text of every group with an id in an SVG file (id -> its text, stripped)."""
    return {g.get("id"): "".join(g.itertext()).strip() for g in ET.parse(path).iter("{http://www.w3.org/2000/svg}g")
            if g.get("id")}


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
                                       "travel": t.travel, "mode_switch": t.mode_switch})
    assert sum(rev.times.values()) == pytest.approx(t.total, rel=1e-3)      # every second accounted for
    assert rev.total_time == pytest.approx(t.total, abs=1.0)
    assert rev.drift and rev.drift[-1][3] > 0          # the kalman filter's sigma
    # the true drift the harness logged is the one it measured the estimates against
    assert [r[0] for r in rev.true_drift] == pytest.approx([p.t for p in out.drift])
    assert [c for r in rev.true_drift for c in r[1:]] == pytest.approx([c for p in out.drift for c in p.truth])
    assert rev.last_drift_error() == pytest.approx(out.drift[-1].error)


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
    for row in ("slot l1", "pushes (failed)", "instrument time", "drift estimate", "simulated truth",
                "nm from the true drift"):
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


def test_the_table_names_a_rod_slot_s_object_by_the_run_s_id(rod_log):
    """The run identified the scene's rod under another id: the slot's row names the run's
    id (the one its events and pushes use), the scene's only as the truth."""
    path, out = rod_log
    run_id = {a["target"]: a["object"] for a in read_log(path).last("/result").data["assignment"]}["bar"]
    scene_id = out.ids[run_id]
    assert scene_id != run_id, "the scene names the rod otherwise than the run"
    rev = review(path)
    bar = next(s for s in rev.slots if s.target == "bar")
    assert (bar.object, bar.truth) == (run_id, scene_id)
    assert bar.pose.kind == "rod" and bar.error == pytest.approx(out.errors["bar"])
    from rich.console import Console

    console = Console(file=io.StringIO(), width=250)
    print_review(rev, console)
    row = next(line for line in console.file.getvalue().splitlines() if "slot bar" in line)
    assert re.search(rf"(filled|missed) by {run_id} \(truth: scene id {scene_id}\):", row), row
    assert f"by {scene_id}" not in row


def test_the_plot_labels_slots_and_the_run_s_objects_and_zooms_on_slot_errors(logged, tmp_path):
    rev = review(logged[0])
    svg = tmp_path / "review.svg"
    plot_review(rev, svg)
    texts = svg_texts(svg)
    for panel in ("before", "after"):
        assert {t.id for t in rev.layout.targets} <= {texts.get(f"{panel}-slot-label-{t.id}")
                                                     for t in rev.layout.targets}
    for oid in {b.id for b in rev.final}:                   # the run's ids, at its objects
        assert texts[f"after-object-label-{oid}"] == oid
    for b in rev.truth_final:                               # the scene's, only as the truth
        assert texts[f"after-truth-label-{b.id}"] == f"truth: scene id {b.id}"
    assert not {b.id for b in rev.truth_final} & {b.id for b in rev.final}, "the two id spaces differ here"
    assert re.search(r'<image [^>]*id="before-full-scan"', svg.read_text())     # the scan underneath
    # the slot with the largest error is zoomed, its error vector drawn, its figure stated
    worst = max(rev.slots, key=lambda s: s.error)
    assert f"zoom-{worst.target}" in texts and f"error-{worst.target}" in texts
    assert f"slot {worst.target}: {worst.error:.1f} nm off" in texts[f"zoom-{worst.target}"]
    assert re.search(r"vectors x\d+", texts[f"zoom-{worst.target}"])


def test_a_dry_run_s_plot_draws_the_true_drift_beside_the_estimate(logged, belief_log):
    path, out = logged

    def drift_lines(rev):
        fig = review_figure(rev)
        ax = next(a for a in fig.axes if a.get_gid() == "drift")
        return {line.get_gid(): line for line in ax.get_lines()}

    lines = drift_lines(review(path))
    for i, axis in enumerate("xy"):
        truth, estimate = lines[f"true-drift-{axis}"], lines[f"drift-{axis}"]
        assert list(truth.get_xdata()) == pytest.approx([p.t / 60 for p in out.drift])
        assert list(truth.get_ydata()) == pytest.approx([p.truth[i] for p in out.drift])
        assert list(estimate.get_ydata()) == pytest.approx([p.estimate[i] for p in out.drift])
    assert "true-drift-x" not in drift_lines(review(belief_log[0]))    # a real run has no truth
