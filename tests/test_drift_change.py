"""The drift that changes: settling (acceleration) and smooth jumps, in the model and in scene files."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nanoasm.errors import InputError
from nanoasm.world.params import CreepParams, DriftChangeParams, DriftParams, WorldParams
from nanoasm.world.scene import Scene, scene_from_dict
from nanoasm.world.sim import DriftModel, SimulatedAFM

STILL = DriftParams(velocity=(0.0, 0.0), random_walk=0.0)


def model(seed: int = 0, drift: DriftParams = STILL, **change) -> DriftModel:
    return DriftModel(drift, CreepParams(), np.random.default_rng(seed), change=DriftChangeParams(**change))


def offsets(m: DriftModel, t) -> np.ndarray:
    return np.stack(m.thermal(t), axis=-1)


# -- acceleration ------------------------------------------------------------------------------------

def test_steady_part_is_v_t_plus_half_a_t_squared():
    v, a = (0.08, -0.05), (2e-5, 7e-5)
    m = model(1, DriftParams(velocity=v, random_walk=0.0), acceleration=a)
    t = np.array([0.0, 1.5, 1000.0, 36000.0])
    dx, dy = m.thermal(t)
    np.testing.assert_allclose(dx, v[0] * t + a[0] * t**2 / 2, rtol=1e-12, atol=0)
    np.testing.assert_allclose(dy, v[1] * t + a[1] * t**2 / 2, rtol=1e-12, atol=0)
    vx, vy = m.velocity(t)
    np.testing.assert_allclose(vx, v[0] + a[0] * t, rtol=1e-12)
    np.testing.assert_allclose(vy, v[1] + a[1] * t, rtol=1e-12)


def test_acceleration_adds_to_the_same_random_walk():
    walk = DriftParams(velocity=(0.01, 0.02), random_walk=0.2)
    t = np.linspace(0.0, 5000.0, 777)
    plain = offsets(model(4, walk), t)
    settling = offsets(model(4, walk, acceleration=(1e-4, -3e-5)), t)
    np.testing.assert_allclose(settling - plain, 0.5 * t[:, None] ** 2 * np.array([1e-4, -3e-5]),
                               rtol=1e-9, atol=1e-9)


# -- jumps ----------------------------------------------------------------------------------------------

def test_a_jump_moves_the_offset_by_its_size_smoothly():
    m = model(2, jump=40.0, jump_at=300.0, jump_duration=2.0)
    before, after = offsets(m, np.array([0.0, 299.999, 300.0])), offsets(m, np.array([302.0, 310.0, 9000.0]))
    assert np.all(before == 0.0)
    np.testing.assert_allclose(after, np.broadcast_to(after[0], after.shape), atol=1e-12)
    assert math.hypot(*after[0]) == pytest.approx(40.0, rel=1e-12)
    # continuous, with a finite velocity that is the offset's derivative and vanishes at both ends
    t = np.linspace(299.0, 303.0, 4001)
    o, v = offsets(m, t), np.stack(m.velocity(t), axis=-1)
    assert np.max(np.hypot(*np.diff(o, axis=0).T)) <= 1.5 * 40.0 / 2.0 * 1e-3 + 1e-9
    assert np.max(np.hypot(*v.T)) == pytest.approx(1.5 * 40.0 / 2.0, rel=1e-3)
    np.testing.assert_allclose(m.velocity(300.0), (0.0, 0.0), atol=1e-12)
    np.testing.assert_allclose(m.velocity(302.0), (0.0, 0.0), atol=1e-12)
    h = 1e-5
    mid = np.array([300.3, 301.0, 301.9])
    fd = (offsets(m, mid + h) - offsets(m, mid - h)) / (2 * h)
    np.testing.assert_allclose(np.stack(m.velocity(mid), axis=-1), fd, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("every, duration", [(100.0, 1.0), (0.7, 2.0)])  # apart; overlapping steps
def test_repeated_jumps_each_move_the_offset_by_the_size(every, duration):
    m = model(3, jump=25.0, jump_at=50.0, jump_every=every, jump_duration=duration)
    k = np.arange(12)
    settled = offsets(m, 50.0 + k * every + duration + 1e-6)  # just after jump k ends
    if every >= duration:
        steps = np.diff(settled, axis=0)
        np.testing.assert_allclose(np.hypot(*steps.T), 25.0, rtol=1e-9)
        assert len({tuple(np.round(s, 6)) for s in steps}) == len(steps)   # own direction each
    t = np.linspace(40.0, 50.0 + 12 * every + duration, 20001)
    o, v = offsets(m, t), np.stack(m.velocity(t), axis=-1)
    assert np.all(np.isfinite(o)) and np.all(np.isfinite(v))
    assert np.max(np.hypot(*v.T)) <= 1.5 * 25.0 / duration * math.ceil(duration / every + 1)
    assert np.max(np.hypot(*np.diff(o, axis=0).T)) <= np.max(np.hypot(*v.T)) * (t[1] - t[0]) * 1.01


def test_jumps_are_deterministic_per_seed_and_independent_of_query_order():
    t = np.sort(np.random.default_rng(0).uniform(0.0, 200000.0, 3000))  # > 256 jumps: several streams
    kw = dict(jump=10.0, jump_at=30.0, jump_every=60.0, jump_duration=5.0)
    whole = offsets(model(7, **kw), t)
    np.testing.assert_array_equal(whole, offsets(model(7, **kw), t))
    assert not np.allclose(whole, offsets(model(8, **kw), t))
    backwards = model(7, **kw)
    parts = np.vstack([offsets(backwards, t[i:i + 500]) for i in range(2500, -1, -500)][::-1])
    np.testing.assert_array_equal(parts, whole)


def test_jumps_leave_the_random_walk_draws_alone():
    walk = DriftParams(velocity=(0.05, 0.0), random_walk=0.3)
    t = np.linspace(0.0, 3000.0, 1501)
    diff = offsets(model(5, walk, jump=20.0, jump_at=1000.0), t) - offsets(model(5, walk), t)
    np.testing.assert_array_equal(diff[t <= 1000.0], 0.0)
    np.testing.assert_allclose(np.hypot(*diff[t >= 1001.0].T), 20.0, rtol=1e-9)


def test_the_default_table_changes_nothing_bit_for_bit():
    walk = DriftParams(velocity=(0.06, -0.04), random_walk=0.1)
    t = np.linspace(0.0, 20000.0, 4001)
    plain = DriftModel(walk, CreepParams(), np.random.default_rng(9))
    default = DriftModel(walk, CreepParams(), np.random.default_rng(9), change=DriftChangeParams())
    for a, b in ((plain.thermal(t), default.thermal(t)), (plain.velocity(t), default.velocity(t)),
                 (plain.offset(t), default.offset(t))):
        assert np.asarray(a).tobytes() == np.asarray(b).tobytes()
    assert plain.thermal(123.4) == default.thermal(123.4)


def test_the_simulated_afm_follows_the_scene_table():
    change = DriftChangeParams(acceleration=(1e-3, 0.0), jump=30.0, jump_at=100.0)
    base = Scene((1000.0, 1000.0), seed=3)
    changed = Scene((1000.0, 1000.0), params=WorldParams(drift_change=change), seed=3)
    a, b = SimulatedAFM(base), SimulatedAFM(changed)
    assert a.true_offset(50.0)[0] + 0.5 * 1e-3 * 50.0**2 == pytest.approx(b.true_offset(50.0)[0], abs=1e-9)
    assert a.true_offset(50.0)[1] == pytest.approx(b.true_offset(50.0)[1], abs=1e-9)
    jump = np.subtract(b.true_offset(500.0), a.true_offset(500.0)) - (0.5 * 1e-3 * 500.0**2, 0.0)
    assert math.hypot(*jump) == pytest.approx(30.0, rel=1e-9)


# -- scene files ------------------------------------------------------------------------------------

SCENE = {"format": "nanoasm.scene/1", "area": [2000, 2000],
         "object": [{"kind": "particle", "at": [500, 500], "diameter": 90}]}


def test_the_table_round_trips_through_a_scene_file():
    table = {"acceleration": [3e-5, -1e-5], "jump": 25.0, "jump_at": 900.0, "jump_every": 1800.0,
             "jump_duration": 2.5}
    scene = scene_from_dict({**SCENE, "drift_change": table}, "s.toml")
    assert scene.params.drift_change == DriftChangeParams((3e-5, -1e-5), 25.0, 900.0, 1800.0, 2.5)
    assert scene.to_dict()["drift_change"] == table
    assert scene_from_dict(scene.to_dict(), "again.toml") == scene
    partial = scene_from_dict({**SCENE, "drift_change": {"jump": 5}}, "s.toml")
    assert partial.to_dict()["drift_change"] == {"jump": 5.0}
    assert "drift_change" not in scene_from_dict(SCENE).to_dict()


@pytest.mark.parametrize("table, message", [
    ({"acceleration": [0.0, math.inf]}, "s.toml: drift_change.acceleration: y must be finite, got inf"),
    ({"jump": math.nan}, "s.toml: drift_change.jump: must be finite, got nan"),
    ({"jump": -5.0}, "s.toml: drift_change.jump: must not be negative, got -5.0"),
    ({"jump_at": -1.0}, "s.toml: drift_change.jump_at: must not be negative, got -1.0"),
    ({"jump_every": -60.0}, "s.toml: drift_change.jump_every: must not be negative, got -60.0"),
    ({"jump_duration": 0.0}, "s.toml: drift_change.jump_duration: must be positive, got 0.0"),
    ({"jump_duration": -1.0}, "s.toml: drift_change.jump_duration: must be positive, got -1.0"),
    ({"jumps": 1.0}, "s.toml: drift_change.jumps: unknown key (did you mean 'jump'"),
])
def test_bad_values_are_located(table, message):
    with pytest.raises(InputError) as e:
        scene_from_dict({**SCENE, "drift_change": table}, "s.toml")
    assert str(e.value).startswith(message), str(e.value)
