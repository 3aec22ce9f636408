"""The rod search's fast checks answer as the free space's own (issue 14, planning time).

:meth:`FreeSpace.nearby` asks the trees once for the entries near a box, and
:meth:`Nearby.all_free` then tests footprints in the box against those alone; a macro's
sweep is simulated once in the rod's own frame and moved rigidly to each pose. Both must
give what the direct checks give, or the search finds other (or no) pushes.
"""

from __future__ import annotations

import numpy as np
import pytest
import shapely
from hypothesis import given, settings, strategies as st

from nanoasm.bodies import Body
from nanoasm.planner import PlanOptions
from nanoasm.planner.freespace import FreeSpace, _all_inside
from nanoasm.planner.rods import _cores_of, _half, _place, _sweep_ends, capsule_cores, capsule_ends, macro_library


def _space(seed: int, clearance: float) -> FreeSpace:
    rng = np.random.default_rng(seed)
    fixed = [(shapely.box(x, y, x + w, y + h), 0.0) for x, y, w, h in
             zip(rng.uniform(0, 1800, 4), rng.uniform(0, 1800, 4), rng.uniform(20, 300, 4), rng.uniform(20, 300, 4))]
    fixed.append((shapely.LineString([(100, 1900), (900, 1700)]), 15.0))       # a wire
    bodies = {f"p{i}": Body(f"p{i}", "particle", (float(x), float(y)), float(d))
              for i, (x, y, d) in enumerate(zip(rng.uniform(0, 2000, 25), rng.uniform(0, 2000, 25),
                                                rng.uniform(30, 90, 25)))}
    bodies["r"] = Body("r", "rod", (1000.0, 1000.0), 40.0, 30.0, 500.0)
    return FreeSpace((2000.0, 2000.0), fixed, bodies, clearance)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 50), x=st.floats(0, 2000), y=st.floats(0, 2000), angle=st.floats(-180, 180),
       length=st.floats(40, 900), radius=st.floats(1, 60), clearance=st.sampled_from([None, 0.0, 12.0]),
       exempt=st.sampled_from([frozenset(), frozenset({0, 2})]), ignore=st.sampled_from([(), ("r",), ("p3", "r")]))
def test_nearby_answers_as_the_space_does(seed, x, y, angle, length, radius, clearance, exempt, ignore):
    space = _space(seed, 25.0)
    t = np.linspace(0.0, 1.0, 7)
    cores = capsule_cores(x + 60 * t, y - 40 * t, angle + 20 * t, length, 2 * radius)
    b = shapely.bounds(cores)
    near = space.nearby((b[:, 0].min(), b[:, 1].min(), b[:, 2].max(), b[:, 3].max()), radius, clearance)
    assert near.all_free(cores, radius, ignore, exempt, clearance) == space.all_free(cores, radius, ignore,
                                                                                     exempt, clearance)
    for k in range(len(cores)):       # one footprint at a time too
        assert near.all_free(cores[k:k + 1], radius, ignore, exempt, clearance) == \
            space.is_free(cores[k], radius, ignore, exempt, clearance)


def test_nearby_refuses_a_footprint_beyond_its_reach():
    space = _space(0, 25.0)
    near = space.nearby((900.0, 900.0, 1100.0, 1100.0), 10.0, 0.0)
    with pytest.raises(ValueError, match="beyond the reach"):
        near.all_free(shapely.points([(1000.0, 1000.0)]), 20.0, clearance=0.0)


@settings(max_examples=40, deadline=None)
@given(x=st.floats(300, 3700), y=st.floats(300, 3700), angle=st.floats(-400, 400), k=st.integers(0, 47))
def test_a_macros_sweep_moved_to_a_pose_is_the_sweep_made_there(x, y, angle, k):
    opts = PlanOptions()
    rod = Body("r", "rod", (x, y), 30.0, angle, 600.0)
    macros = macro_library(rod, opts, (opts.rod_swing, opts.rod_swing / 2), quads=True)
    m = macros[k % len(macros)]
    c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
    lx, ly = m.sweep[..., 0], m.sweep[..., 1]
    moved = np.stack([x + c * lx - s * ly, y + s * lx + c * ly], axis=-1)
    prev, made = rod, []
    for local in m.poses:
        after = _place(rod, local)
        made.append(_sweep_ends(prev, after))
        prev = after
    made = np.concatenate(made)
    assert moved.shape == made.shape
    assert np.abs(moved - made).max() < 1e-6
    assert len(_cores_of(moved, _half(rod))) == len(moved)


@settings(max_examples=200, deadline=None)
@given(x=st.floats(-100, 2100), y=st.floats(-100, 2100), angle=st.floats(-180, 180),
       length=st.sampled_from([0.0, 40.0, 600.0, 1900.0]), radius=st.floats(0, 80))
def test_inside_from_the_ends_is_inside_from_the_cores(x, y, angle, length, radius):
    """The search's area check from a sweep's end coordinates (``inside_box`` of their
    bounds, as ``RodController._realise`` makes it) answers as the geometries' bounds do
    (``_all_inside``), for segments and for points (no length)."""
    t = np.linspace(0.0, 1.0, 9)
    ends = capsule_ends(x + 90 * t, y - 70 * t, angle + 30 * t, length / 2)
    space = FreeSpace((2000.0, 2000.0), [], {}, 0.0)
    flat = ends.reshape(-1, 2)
    assert space.inside_box(*flat.min(axis=0), *flat.max(axis=0), radius) == \
        _all_inside(_cores_of(ends, length / 2), radius, space.area)


def _plain_hits(space: FreeSpace, geom, radius: float, clearance) -> list[str]:
    """Every movable body within reach of the footprint, by the definition: one distance each."""
    reach = radius + (space.clearance if clearance is None else clearance)
    return sorted(i for i, b in space.bodies.items() if shapely.distance(geom, b.geometry()) < reach + b.radius - 1e-9)


def _plain_slack(space: FreeSpace, geom, radius: float, ignore, horizon: float) -> float:
    x0, y0, x1, y1 = geom.bounds
    best = min(x0, y0, space.area[0] - x1, space.area[1] - y1) - radius
    reach = radius + space.clearance
    for g, r in zip(space._fixed, space._fixed_r):
        best = min(best, float(shapely.distance(geom, g)) - r - reach)
    for i, b in space.bodies.items():
        if i not in ignore:
            best = min(best, float(shapely.distance(geom, b.geometry())) - b.radius - reach)
    return min(best, horizon)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 50),
       moves=st.lists(st.tuples(st.integers(0, 27), st.floats(0, 2000), st.floats(0, 2000), st.floats(20, 140),
                                st.booleans()), max_size=8),
       queries=st.lists(st.tuples(st.floats(0, 2000), st.floats(0, 2000), st.floats(-300, 300), st.floats(-300, 300),
                                  st.floats(1, 60), st.sampled_from([None, 0.0, 12.0])), min_size=1, max_size=6),
       ignore=st.sampled_from([(), ("r",), ("p3", "r")]))
def test_the_movable_bodies_found_by_their_boxes_are_those_within_reach(seed, moves, queries, ignore):
    """The movable bodies' index (boxes updated in place as bodies move, grow, arrive)
    finds, for points, segments and sweeps, exactly the bodies the definition finds one by
    one, and the slack the definition gives, between and after moves."""
    space = _space(seed, 25.0)
    for step in [*moves, None]:
        for qx, qy, dx, dy, radius, clearance in queries:
            for geom in (shapely.Point(qx, qy), shapely.LineString([(qx, qy), (qx + dx + 1.0, qy + dy)])):
                want = [i for i in _plain_hits(space, geom, radius, clearance) if i not in ignore]
                assert space.blockers(geom, radius, ignore, clearance) == want
                assert space.slack(geom, radius, ignore) == _plain_slack(space, geom, radius, set(ignore), 1e3)
            near = space.bodies[sorted(space.bodies)[int(qx) % len(space.bodies)]]      # one just within reach
            reach = radius + (space.clearance if clearance is None else clearance) + 0.5 * near.radius
            cores = np.array([shapely.Point(qx + dx * t, qy + dy * t) for t in (0.0, 0.5, 1.0)]
                             + [shapely.Point(near.at[0] + reach, near.at[1])], dtype=object)
            want = [i for i in _plain_hits(space, cores[-1], radius, clearance) if i not in ignore]
            assert space.blockers(cores[-1], radius, ignore, clearance) == want
            free = all(not [i for i in _plain_hits(space, g, radius, clearance) if i not in ignore] for g in cores)
            inside = _all_inside(cores, radius, space.area)
            clear = not any(space.fixed_hits(g, radius, clearance).size for g in cores)
            assert space.all_free(cores, radius, ignore, clearance=clearance) == (inside and clear and free)
        if step is None:
            break
        k, x, y, d, rod = step
        oid = "r" if k == 27 else f"p{k}"       # 26: a body new to the space
        body = (Body(oid, "rod", (x, y), d / 3, 40.0 + x / 10, d * 4) if rod else Body(oid, "particle", (x, y), d))
        space.move(body)
