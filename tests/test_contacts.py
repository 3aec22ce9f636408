"""Object-object contacts: no interpenetration, chains propagate, idle objects stay idle."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from nanoasm.bodies import Body, overlapping_pairs
from nanoasm.world.params import VdwParams
from nanoasm.world.sim.contact_space import ContactSpace, resolve_contacts


def particle(i, x, y, d=100.0) -> Body:
    return Body(f"p{i}", "particle", (float(x), float(y)), d)


def rod(i, x, y, angle, length=1300.0, d=100.0) -> Body:
    return Body(f"r{i}", "rod", (float(x), float(y)), d, angle=float(angle), length=float(length))


def no_overlap(bodies) -> bool:
    return overlapping_pairs(list(bodies), limit=0) == []


# -- basic behaviour -------------------------------------------------------------------------------

def test_a_push_into_free_space_moves_only_the_driver():
    bodies = [particle(0, 0, 0), particle(1, 0, 500), particle(2, 1000, -300)]
    space = ContactSpace(bodies)
    assert space.push(0, (400.0, 0.0)) == [0]
    assert space.bodies[0].at == pytest.approx((400.0, 0.0))
    assert space.bodies[1:] == tuple(bodies[1:])


def test_a_chain_propagates_along_the_push():
    gaps = [0.0, 30.0, 0.0, 55.0, 10.0]  # touching and nearly touching neighbours
    xs = np.cumsum([0.0] + [100.0 + g for g in gaps])
    bodies = [particle(i, x, 0) for i, x in enumerate(xs)]
    bystander = particle(99, 300, 400)
    space = ContactSpace([*bodies, bystander])
    moved = space.push(0, (600.0, 0.0))
    assert moved == list(range(len(bodies)))
    centres = space.centres()
    # everything ends packed ahead of the driver, in order, touching
    np.testing.assert_allclose(centres[: len(bodies), 0], 600.0 + 100.0 * np.arange(len(bodies)), atol=1e-3)
    np.testing.assert_allclose(centres[: len(bodies), 1], 0.0, atol=1e-9)
    assert space.bodies[-1] == bystander
    assert no_overlap(space.bodies)


def test_a_glancing_push_sends_the_other_sideways():
    space = ContactSpace([particle(0, 0, 0), particle(1, 300, 60)])
    space.push(0, (600.0, 0.0))
    other = space.centres()[1]
    assert other[1] > 60.0  # deflected away from the driver's line
    assert no_overlap(space.bodies)


def test_a_rod_shoved_by_a_particle_translates_only():
    r = rod(0, 1000, 0, angle=90)
    space = ContactSpace([particle(1, 500, 100), r])
    space.push(0, (600.0, 0.0))
    moved_rod = space.bodies[1]
    assert moved_rod.angle == r.angle and moved_rod.length == r.length
    assert moved_rod.at[0] > 1000.0 and moved_rod.at[1] == pytest.approx(0.0, abs=1e-6)
    assert no_overlap(space.bodies)


def test_a_rod_driver_sweeps_particles_along():
    row = [particle(i, 800, y) for i, y in enumerate(range(-600, 601, 200))]
    space = ContactSpace([rod(99, 400, 0, angle=90), *row])
    moved = space.push(0, (700.0, 0.0))
    assert moved == list(range(len(row) + 1))
    assert no_overlap(space.bodies)
    assert np.all(space.centres()[1:, 0] >= 1100.0 + 100.0 - 1e-6)


def test_pushing_into_a_packed_cluster_settles():
    # hexagonal packing of touching particles, hit in its middle
    pts = [(100.0 * (i + 0.5 * (j % 2)), 100.0 * math.sqrt(3) / 2 * j) for i in range(6) for j in range(6)]
    bodies = [particle(k, x + 1000, y) for k, (x, y) in enumerate(pts)]
    space = ContactSpace([particle(999, 600, 220), *bodies])
    space.push(0, (700.0, 0.0))
    assert no_overlap(space.bodies)
    assert space.centres()[0] == pytest.approx((1300.0, 220.0))


def test_resolve_contacts_is_one_push_on_a_fresh_space():
    bodies = [particle(0, 0, 0), particle(1, 150, 10), rod(2, 400, 0, angle=30)]
    space = ContactSpace(bodies)
    space.push(0, (500.0, 20.0))
    assert resolve_contacts(bodies, 0, (500.0, 20.0)) == list(space.bodies)


def test_bad_pushes_are_refused():
    space = ContactSpace([particle(0, 0, 0)])
    with pytest.raises(IndexError):
        space.push(1, (1.0, 0.0))
    with pytest.raises(ValueError, match="finite"):
        space.push(0, (math.nan, 0.0))
    with pytest.raises(ValueError, match="rng"):
        space.push(0, (1.0, 0.0), vdw=VdwParams())


# -- van der Waals error ---------------------------------------------------------------------------

def test_no_error_far_from_others_and_no_draw():
    space = ContactSpace([particle(0, 0, 0), particle(1, 2000, 0)])
    rng = np.random.default_rng(1)
    state = rng.bit_generator.state
    space.push(0, (500.0, 0.0), rng=rng, vdw=VdwParams(range=20, amplitude=5))
    assert space.centres()[0] == pytest.approx((500.0, 0.0))
    assert rng.bit_generator.state == state


def test_error_near_others_is_seeded_and_leaves_no_overlap():
    def run(seed):
        space = ContactSpace([particle(0, 0, 0), particle(1, 700, 0), particle(2, 800, 100)])
        space.push(0, (595.0, 0.0), rng=np.random.default_rng(seed), vdw=VdwParams(range=20, amplitude=5))
        return space

    a, b, c = run(4), run(4), run(5)
    np.testing.assert_array_equal(a.centres(), b.centres())
    assert not np.allclose(a.centres(), c.centres())
    assert a.centres()[0] != pytest.approx((595.0, 0.0))
    assert no_overlap(a.bodies) and no_overlap(c.bodies)


# -- properties ------------------------------------------------------------------------------------

@st.composite
def scenes(draw):
    n = draw(st.integers(2, 20))
    side = draw(st.sampled_from([700.0, 3000.0]))  # crowded or sparse
    bodies = []
    for i in range(n):
        x = draw(st.floats(0, side))
        y = draw(st.floats(0, side))
        d = draw(st.sampled_from([40.0, 100.0, 150.0]))
        if draw(st.integers(0, 3)) == 0:
            length = draw(st.floats(3 * d, 14 * d))
            bodies.append(rod(i, x, y, draw(st.floats(0, 180)), length, d))
        else:
            bodies.append(particle(i, x, y, d))
    kept = []
    for b in bodies:  # drop bodies that overlap earlier ones: a valid scene
        if not overlapping_pairs([*kept, b], limit=1):
            kept.append(b)
    assume(len(kept) >= 2)
    return kept


@given(scenes(), st.data())
def test_no_interpenetration_after_any_push(bodies, data):
    i = data.draw(st.integers(0, len(bodies) - 1))
    d = (data.draw(st.floats(-1500, 1500)), data.draw(st.floats(-1500, 1500)))
    use_vdw = data.draw(st.booleans())
    space = ContactSpace(bodies)
    moved = space.push(i, d, rng=np.random.default_rng(0) if use_vdw else None,
                       vdw=VdwParams() if use_vdw else None)
    after = space.bodies
    assert no_overlap(after)
    for k in range(len(bodies)):
        if k not in moved:
            assert after[k] == bodies[k]
        assert after[k].angle == bodies[k].angle  # translation only
    if not use_vdw:
        expect = (bodies[i].at[0] + d[0], bodies[i].at[1] + d[1])
        assert after[i].at == pytest.approx(expect, abs=1e-6)


@given(scenes(), st.data())
def test_bodies_out_of_reach_never_move(bodies, data):
    i = data.draw(st.integers(0, len(bodies) - 1))
    d = (data.draw(st.floats(-800, 800)), data.draw(st.floats(-800, 800)))
    reach = math.hypot(*d) + sum(2 * b.radius + (b.length or 0) for b in bodies)
    x0, y0 = bodies[i].at
    far = particle(1000, x0 + reach + 100, y0)
    space = ContactSpace([*bodies, far])
    space.push(i, d)
    assert space.bodies[-1] == far


# -- cost -------------------------------------------------------------------------------------------

def _row_with_idle(n_idle: int) -> list[Body]:
    row = [particle(i, 100.0 * i, 0) for i in range(5)]
    side = math.ceil(math.sqrt(n_idle))
    idle = [particle(100 + k, 5000 + 300.0 * (k % side), 5000 + 300.0 * (k // side)) for k in range(n_idle)]
    return row + idle


def test_cost_does_not_grow_with_idle_objects():
    report = {}
    for n_idle in (10, 1000):
        space = ContactSpace(_row_with_idle(n_idle))
        t0 = time.perf_counter()
        space.push(0, (800.0, 0.0))
        report[n_idle] = (space.pair_tests, time.perf_counter() - t0)
    print("\ncontact push: pair tests and seconds with 10 vs 1000 idle objects:", report)
    assert report[10][0] == report[1000][0] > 0
