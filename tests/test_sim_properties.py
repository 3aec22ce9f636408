"""Invariants of the simulated AFM under any push, and the cost of idle objects."""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import pytest
import shapely
from hypothesis import given
from hypothesis import strategies as st
from nanoasm.world.params import WorldParams
from nanoasm.world.random_scene import SceneSpec, random_scene
from nanoasm.world.sim import SimulatedAFM
from nanoasm.world.sim import push as sim_push
from nanoasm.world.sim import rods as sim_rods
from simkit import particle, path_codes, push, rod, world

from nanoasm.bodies import Body, overlapping_pairs


def _finite(block, bodies) -> bool:
    arrays = [block.s_n, block.s_l] + [np.array([*b.at, b.angle or 0.0, b.length or 0.0]) for b in bodies]
    return all(np.all(np.isfinite(a)) for a in arrays)


@given(seed=st.integers(0, 10_000), n_particles=st.integers(2, 7), n_rods=st.integers(0, 2),
       target=st.integers(0, 8), angle=st.floats(0, 360), aim=st.floats(-0.6, 0.6),
       length=st.floats(50, 600))
def test_any_push_keeps_objects_apart_moves_only_what_it_reaches_and_stays_finite(
        seed, n_particles, n_rods, target, angle, aim, length):
    spec = SceneSpec(area=(1500.0, 1500.0), particles=n_particles, rods=n_rods,
                     particle_diameter=(40.0, 120.0), rod_length=(250.0, 600.0),
                     rod_diameter=(50.0, 80.0), gap=2.0)
    placed = random_scene(spec, seed)                       # moved 1 µm in from the scanner's edge
    scene = dataclasses.replace(placed, area=(5000.0, 5000.0), objects=tuple(
        dataclasses.replace(b, at=(b.at[0] + 1000.0, b.at[1] + 1000.0)) for b in placed.objects))
    sim = SimulatedAFM(scene, seed=seed)
    obj = scene.objects[target % len(scene.objects)]
    u = np.array([math.cos(math.radians(angle)), math.sin(math.radians(angle))])
    v = np.array([-u[1], u[0]])
    reach = (obj.length or obj.diameter) / 2
    start = np.array(obj.at) - (reach + 60.0) * u + aim * reach * v
    end = start + (reach + 60.0 + length) * u
    block, _ = push(sim, start, end)
    after = sim.truth()

    assert overlapping_pairs(after, limit=0) == []
    assert _finite(block, after)
    path = shapely.LineString([start, end])
    far = length + 60.0 + sum(b.diameter for b in scene.objects) + 2 * reach + 100.0
    for before, now in zip(scene.objects, after):
        if shapely.distance(before.geometry(), path) > far:
            assert now is before
        assert now.id == before.id


def _wire(at, angle=0.0, length=1200.0, d=30.0, id="w") -> Body:
    return Body(id, "rod", at, d, angle, length)


def _cross_overlaps(sim) -> list:
    """Overlapping footprints of different objects (a wire's segments overlap at their joints)."""
    units = sim.footprints()
    owner = [b.id.split("#")[0] for b in units]
    return [(i, j) for i, j in overlapping_pairs(units, limit=0) if owner[i] != owner[j]]


@pytest.mark.parametrize("start, end", [((1500, 1700), (1500, 2300)),    # the wire into the particles
                                        ((1300, 2200), (1300, 1800))])   # a particle into the wire
def test_wires_and_particles_never_interpenetrate(start, end):
    objs = [_wire((1500.0, 2000.0)), particle((1500, 2100), d=60, id="a"),
            particle((1300, 2090), d=60, id="b"), particle((1700, 2075), d=40, id="c")]
    sim = world(objs)
    block, _ = push(sim, start, end)
    assert _cross_overlaps(sim) == []
    assert _finite(block, sim.truth())
    assert sim.truth() != tuple(objs)


class RodCodeRan(Exception):
    pass


def test_a_particle_only_scene_never_runs_rod_code(monkeypatch):
    def boom(*args, **kwargs):
        raise RodCodeRan
    for module, name in ((sim_rods, "rod_step"), (sim_push, "rod_motion"), (sim_push, "rod_push_outcome"),
                         (sim_push, "wire_motion")):
        monkeypatch.setattr(module, name, boom)
    sim = world([particle((2000, 2000), id="a"), particle((2060, 2010), id="b"), particle((2400, 2400), id="c")])
    push(sim, (1800, 2000), (2500, 2000))
    push(sim, (2400, 2200), (2400, 2600))
    assert sim.diagnostics()["pushes"] == 2
    with pytest.raises(RodCodeRan):                           # the patches are the live names
        push(world([rod((2000, 2000), 0.0, 400.0)]), (1850, 1900), (1850, 2100))
    with pytest.raises(RodCodeRan):
        push(world([_wire((2000.0, 2000.0))]), (2000, 1900), (2000, 2100))


def _lifted_sweep_time(n_objects: int) -> tuple[float, int]:
    spec = SceneSpec(area=(40000.0, 40000.0), particles=n_objects, gap=50.0)
    sim = SimulatedAFM(random_scene(spec, 5), seed=5, params=WorldParams())
    cfg = sim.config
    lift = cfg.lift
    xs = np.linspace(500.0, 39500.0, 40)
    pts = [(x, 500.0 if k % 2 == 0 else 39500.0, lift) for k, x in enumerate(xs)]
    codes = path_codes(sim, pts)
    times = []
    for _ in range(3):
        t = time.perf_counter()
        sim.write(codes)
        times.append(time.perf_counter() - t)
        codes = codes[::-1].copy()
        codes = np.vstack([path_codes(sim, [tuple(cfg.codes_to_nm(codes[0]))]), codes])
    return float(np.median(times)), codes.shape[0]


def test_idle_objects_cost_nothing_on_a_lifted_chunk():
    t10, n = _lifted_sweep_time(10)
    t1000, _ = _lifted_sweep_time(1000)
    assert n > 20_000
    assert t1000 < 2.5 * t10 + 0.03                          # medians of 3; ~17 ms each
