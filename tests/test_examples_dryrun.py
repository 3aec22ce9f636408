"""End-to-end dry-runs of the bundled scenes at 0.3 nm/s of drift, fixed seeds: particles
only, rods, and particles with a rod between electrode pads. The targets: at least 95 % of
the feasible slots filled, RMS slot error at most 10 nm."""

from __future__ import annotations

import math

import pytest

from nanoasm.cad.layout import load_layout
from nanoasm.dryrun import dry_run
from nanoasm.examples import path as example
from nanoasm.executor.strategy import ExecOptions
from nanoasm.world.scene import load_scene

#: example name -> world seeds dry-run (each a different simulated world of one scene)
CASES = {"particles": (1, 2, 3), "rods": (2,), "mixed": (1,)}


def _load(name: str):
    return load_scene(example(f"{name}_scene.toml")), load_layout(example(f"{name}.toml"))


@pytest.mark.parametrize("name", sorted(CASES))
def test_bundled_scene_drifts_at_0_3_nm_per_s(name):
    scene, _ = _load(name)
    assert math.hypot(*scene.params.drift.velocity) == pytest.approx(0.3, abs=1e-3)


@pytest.mark.parametrize("name,seed", [(n, s) for n, seeds in sorted(CASES.items()) for s in seeds])
def test_bundled_scene_is_assembled_within_the_targets(name, seed):
    scene, layout = _load(name)
    out = dry_run(scene, layout, seed=seed, options=ExecOptions(strategy="full"))
    assert len(out.filled) >= math.ceil(0.95 * len(layout.targets)), (out.filled, out.summary.unfilled)
    assert out.rms_error <= 10.0, out.errors
