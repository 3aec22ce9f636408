"""End-to-end dry-runs on the bundled example: the executor against the simulated AFM."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest

from nanoasm.cad.layout import load_layout
from nanoasm.dryrun import dry_run
from nanoasm.examples import path as example
from nanoasm.executor.report import report_from_dict
from nanoasm.executor.strategy import STRATEGIES, ExecOptions
from nanoasm.world import sim as simmod
from nanoasm.executor.verdict import RETRY_TURNS
from nanoasm.world.scene import load_scene


@pytest.fixture(scope="module")
def bowtie():
    """The bundled example without its rod slot (rod planning is the slow part)."""
    from dataclasses import replace

    layout = load_layout(example("bowtie.toml"))
    layout = replace(layout, targets=tuple(t for t in layout.targets if t.kind == "particle"))
    return load_scene(example("bowtie_scene.toml")), layout


@pytest.fixture(scope="module")
def runs(bowtie):
    scene, layout = bowtie
    return {s: dry_run(scene, layout, seed=3, options=ExecOptions(strategy=s)) for s in STRATEGIES}


@pytest.mark.parametrize("strategy", STRATEGIES)
def test_every_strategy_runs_to_a_valid_report(runs, bowtie, strategy):
    scene, layout = bowtie
    out = runs[strategy]
    rep = out.report
    # a valid report v1 that round-trips, with every scene object before and after
    assert report_from_dict(json.loads(rep.dumps())) == rep
    ids = {o.id for o in scene.objects}
    assert {o.id for o in rep.initial_objects} == ids == {o.id for o in rep.final_objects}
    assert rep.counts.pushes > 0 and rep.pushed
    assert set(rep.pushed) <= ids
    t = rep.instrument_time
    assert t.full_scan > 60                                    # minutes per full frame
    # the parts account for every second (the approaches into contact included), to the
    # calibration a dry-run makes before its clock starts: within 0.1 % of the total
    parts = t.full_scan + t.local_scan + t.push + t.travel + t.mode_switch
    assert parts == pytest.approx(t.total, rel=1e-3) and t.mode_switch > 0
    old = json.loads(rep.dumps())                           # a report from before mode_switch reads as 0
    del old["instrument_time"]["mode_switch"]
    assert report_from_dict(old).instrument_time == replace(t, mode_switch=0.0)
    assert {a.target for a in rep.assignment} | {u.target for u in rep.unfilled} == \
        {tg.id for tg in layout.targets}
    if strategy == "open-loop":                # no scans but the final check of every slot
        # (a check whose line a neighbour cut goes round again, turned: up to RETRY_TURNS)
        n = len(layout.targets)
        assert n <= rep.counts.local_scans <= n * (1 + len(RETRY_TURNS)) and 0 < t.local_scan < 120
    else:
        assert rep.counts.local_scans >= rep.counts.pushes


def test_the_executor_never_reads_the_simulated_truth(bowtie, monkeypatch):
    scene, layout = bowtie
    calls = []
    real = simmod.SimulatedAFM.truth

    def watched(self):
        import inspect

        caller = inspect.stack()[1]
        calls.append(caller.filename)
        return real(self)

    monkeypatch.setattr(simmod.SimulatedAFM, "truth", watched)
    dry_run(scene, layout, seed=5, options=ExecOptions(strategy="local-scan"))
    assert calls and all(f.endswith("dryrun.py") for f in calls)


def test_a_dry_run_is_reproducible(bowtie):
    scene, layout = bowtie
    a = dry_run(scene, layout, seed=11, options=ExecOptions(strategy="kalman")).report
    b = dry_run(scene, layout, seed=11, options=ExecOptions(strategy="kalman")).report
    strip = lambda r: {k: v for k, v in r.to_dict().items() if k != "wall_time"}  # noqa: E731
    assert strip(a) == strip(b)


@pytest.mark.parametrize("fault", ["stuck_object", "tip_slip", "lost_object", "tip_blunting"])
def test_injected_faults_are_survived(bowtie, fault):
    """With a fault striking 30 % of pushes, the run still ends normally, says what failed,
    and writes a valid report."""
    from dataclasses import replace

    from nanoasm.world.params import FaultParams

    scene, layout = bowtie
    scene = replace(scene, params=replace(scene.params, faults=FaultParams(**{fault: 0.3})))
    out = dry_run(scene, layout, seed=3, options=ExecOptions(strategy="full"))
    rep = out.report
    assert report_from_dict(json.loads(rep.dumps())) == rep
    if fault != "tip_blunting":
        assert out.summary.failures, "the faults went unnoticed"
        assert rep.counts.replans > 0
    # a lost object keeps no slot: its slot is reported unfilled, and why
    assigned = {a.object for a in out.summary.assignment}
    for oid, cause in out.summary.failures:
        if cause == "lost" and oid in out.summary.belief.lost:
            assert oid not in assigned


def test_the_run_harness_reports_what_the_run_believes(runs, bowtie):
    """nanoasm.run's harness in front of the simulated AFM (any Instrument will do): the
    dry-run's very run, reported through the same constructor from what the run
    identified and believes instead of from the truth."""
    from nanoasm.executor.lever_file import InstrumentLever
    from nanoasm.run import run

    scene, layout = bowtie
    dry = runs["local-scan"]
    lever = InstrumentLever(dry.calibration.lever(), baselines=dry.calibration.baselines)   # the dry-run's own
    rep = run(layout, simmod.SimulatedAFM(scene, seed=3), options=ExecOptions(strategy="local-scan"),
              layout_name="particles.toml", lever=lever)
    assert report_from_dict(json.loads(rep.dumps())) == rep
    assert (rep.scene, rep.layout, rep.seed, rep.targets) == (None, "particles.toml", None, layout.targets)
    assert rep.counts == dry.report.counts and rep.unfilled == dry.report.unfilled
    assert rep.instrument_time == dry.report.instrument_time
    summary = dry.summary
    assert rep.assignment == summary.assignment and rep.pushed == tuple(summary.pushed)
    assert [b.id for b in rep.initial_objects] == [o.id for o in summary.env.objects]
    believed = {i: o for i, o in summary.belief.objects.items() if i not in summary.belief.lost}
    assert {b.id: b.at for b in rep.final_objects} == {i: o.at for i, o in believed.items()}


def test_the_run_harness_goes_on_from_a_checkpoint(bowtie):
    """A run resumed by the harness from its second checkpoint (the state as a log gives
    it) ends as the uninterrupted run; its instrument time is its own."""
    from nanoasm.executor.documents import as_dict
    from nanoasm.executor.resume import ResumePoint
    from nanoasm.executor.runlog import to_json
    from nanoasm.run import run

    scene, layout = bowtie
    options = ExecOptions(strategy="local-scan")
    sim = simmod.SimulatedAFM(scene, seed=3)
    kept: dict = {}

    def keep(topic: str, doc) -> None:
        if topic in ("environment", "plan", "checkpoint"):
            kept.setdefault(topic, []).append(json.loads(to_json(as_dict(doc))))
        if topic == "checkpoint" and len(kept["checkpoint"]) == 2:
            kept["sim"] = json.dumps(sim.state_dict(), allow_nan=False)

    whole = run(layout, sim, options=options, subscribers=[keep])
    state = {**kept["checkpoint"][1], "env": kept["environment"][0], "first_plan": kept["plan"][0]}
    state.pop("saved_at", None)                 # resumed at once: no pause to add
    resumed = run(layout, simmod.SimulatedAFM.from_state(scene, json.loads(kept["sim"])), options=options,
                  resume=ResumePoint("stopped.mcap", state, layout, {}))
    assert resumed.assignment == whole.assignment and resumed.counts == whole.counts
    assert 0 < resumed.instrument_time.total < whole.instrument_time.total


def test_ids_are_matched_with_each_row_s_drift_taken_out():
    """A long full scan shifts what its later rows show by more than the objects' spacing
    (800 nm over a 10 µm scan on `wide`): matched by raw position, objects take their
    neighbours' ids; with each row's true drift taken out, each finds itself."""
    from nanoasm.bodies import Body
    from nanoasm.dryrun import match_ids

    truth = tuple(Body(f"s{k}", "particle", (1000.0, 300.0 * k), 60.0) for k in range(1, 9))
    # the drift a row carried grows with the row: half its raw y, so raw = 2 x true
    found = tuple(Body(f"o{k}", "particle", (1000.0, 2 * b.at[1]), 60.0) for k, b in enumerate(truth, start=1))
    right = {f"o{k}": f"s{k}" for k in range(1, 9)}
    assert match_ids(found, truth, shift=lambda at: (0.0, 0.5 * at[1])) == right
    wrong = match_ids(found, truth)
    assert wrong["o1"] == "s2" and len(set(wrong.items()) & set(right.items())) <= 1
