"""Drift references that cannot run out, in whole dry-runs against the simulated truth
(which the harness reads, never the executor): the estimate stays within its own
uncertainty of the true drift, fixed features keep it going when every object is
pushed, and a sudden drift jump is caught by relocalisation."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from nanoasm.dryrun import dry_run
from nanoasm.executor.strategy import ExecOptions
from nanoasm.world.families import family_case

#: 2-dof χ² of probability 0.9973: an error within "3σ" of a 2-D estimate.
CHI2_3SIGMA = 11.829


class Events:
    def __init__(self):
        self.texts: list[str] = []

    def __call__(self, topic, doc):
        if topic == "event":
            self.texts.append(doc.text if hasattr(doc, "text") else doc["text"])


def _with_jump(scene, size: float, at: float):
    change = replace(scene.params.drift_change, jump=size, jump_at=at)
    return replace(scene, params=replace(scene.params, drift_change=change))


@pytest.fixture(scope="module")
def mixed_run():
    scene, layout = family_case("mixed", 1)          # creep 27 % off nominal, the drift changing
    events = Events()
    return dry_run(scene, layout, options=ExecOptions(strategy="full"), subscribers=[events]), layout, events


def test_the_drift_estimate_stays_within_its_uncertainty_of_the_truth(mixed_run):
    out, layout, _ = mixed_run
    pts = out.drift
    assert len(pts) > 20
    rms = math.sqrt(sum(p.error ** 2 for p in pts) / len(pts))
    inside = sum(p.mahalanobis2 <= CHI2_3SIGMA for p in pts) / len(pts)
    assert rms <= 10.0 and inside >= 0.95, (rms, inside)
    assert max(p.sigma for p in pts[1:]) <= 50.0
    assert set(out.filled) == {t.id for t in layout.targets}
    assert set(out.verdict_filled) == set(out.truly_filled) and not out.disagreements


def test_fixed_features_measure_drift_and_cost_little(mixed_run):
    out, _, events = mixed_run
    assert any("fixed feature(s) of the obstacles" in t and not t.startswith("0 ") for t in events.texts)
    t = out.report.instrument_time
    spent = out.summary.purposes["reference"] + out.summary.purposes["relocalise"]
    assert 0.0 < spent <= 0.15 * (t.total - t.full_scan)


def test_a_drift_jump_mid_run_is_caught_by_relocalisation_and_every_slot_still_filled():
    scene, layout = family_case("mixed", 1)
    events = Events()
    out = dry_run(_with_jump(scene, 300.0, 700.0), layout, options=ExecOptions(strategy="full"),
                  subscribers=[events])
    assert any(t.startswith("relocalised by window") for t in events.texts), events.texts
    assert set(out.filled) == {t.id for t in layout.targets} and not out.disagreements
    late = [p for p in out.drift if p.t > 1000.0]
    assert late and max(p.error for p in late) < 15.0
