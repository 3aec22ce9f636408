"""End-to-end dry-runs on the bundled example: the executor against the simulated AFM."""

from __future__ import annotations

import json

import pytest

from nanoasm.cad.layout import load_layout
from nanoasm.dryrun import dry_run
from nanoasm.examples import path as example
from nanoasm.executor.report import report_from_dict
from nanoasm.executor.strategy import STRATEGIES, ExecOptions
from nanoasm.world import sim as simmod
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
    assert t.full_scan + t.local_scan + t.push + t.travel <= t.total + 1e-6
    assert {a.target for a in rep.assignment} | {u.target for u in rep.unfilled} == \
        {tg.id for tg in layout.targets}
    if strategy == "open-loop":
        assert rep.counts.local_scans == 0 and t.local_scan == 0
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
