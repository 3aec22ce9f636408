"""What a 1000-object run keeps or does at once instead of one by one (issue 16) gives what
the one-by-one way gives: the filter's projections of many candidates, the full scan's
row terms kept by row, the scan model read from the filter while its state stands, the
reference choice's batched terms, the slot-filled test through a k-d tree, and the 3-D
view's resting heights."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_scan_surface import decoded

from nanoasm.bodies import Body
from nanoasm.cad.layout import Layout, Tolerance
from nanoasm.drift import DriftFilter, DriftFilterParams
from nanoasm.drift.creep import creep_offset, creep_tau_sensitivity
from nanoasm.executor.belief import Belief
from nanoasm.executor.context import RunContext
from nanoasm.executor.documents import CHECKPOINT, FULL_SCAN
from nanoasm.executor.estimators import Kalman
from nanoasm.executor.foxglove_scenes import timestamp
from nanoasm.executor import reference_choice
from nanoasm.executor.reference_choice import best, best_object, object_candidates
from nanoasm.executor.references import References
from nanoasm.executor.scan_drift import EPS, LAM, ScanDrift, filter_theta
from nanoasm.executor.scan_surface import SURFACE_TOPIC, SurfaceView, surface_grid
from nanoasm.executor.strategy import ExecOptions
from nanoasm.instrument import InstrumentConfig
from nanoasm.planner import PlanOptions
from nanoasm.planner.assign import in_slot, match
from nanoasm.world.environment import EnvObject, Environment

OPTS = ExecOptions()


def _filter(seed: int) -> DriftFilter:
    rng = np.random.default_rng(seed)
    n = 4 + 5
    A = rng.normal(size=(n, n))
    f = DriftFilter(DriftFilterParams(), epoch=0.0, x0=rng.normal(size=n), P0=A @ A.T + np.eye(n), statics=5,
                    start=0.0, learn_creep=True, tau_static=4)
    for k in range(4):
        f.creep.record(5.0 + 3 * k, rng.normal(size=2) * 300.0)
    return f


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 6), st.floats(20.0, 500.0))
def test_the_filters_weighing_of_many_equals_its_projections_one_by_one(seed, k, t):
    f = _filter(seed)
    rng = np.random.default_rng(seed + 1)
    user = f.statics - 1
    S = rng.normal(size=(k, 2, user + 1)) * 10.0
    R = np.diag(rng.uniform(1.0, 9.0, 2))
    covs, gains = f.weigh_many(t, np.eye(2), R, S)
    for j in range(k):
        _, cov = f.projected(t, np.eye(2), S[j])
        assert covs[j] == pytest.approx(cov, rel=1e-12, abs=1e-9)
        assert gains[j] == pytest.approx(f.information(t, np.eye(2), R, S[j]), rel=1e-9, abs=1e-12)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000), st.booleans(), st.lists(st.tuples(st.sampled_from("Mcxo"), st.floats(0.0, 40.0)),
                                                    min_size=1, max_size=12))
def test_the_offset_without_its_covariance_is_the_offsets_to_the_bit(seed, statics, steps):
    """``offset_mean`` against ``offset(t).offset`` (and a filter that never kept an
    answer), asked in either order, at times the filter has and has not predicted to,
    across measurements and moves that change the state and the creep."""
    rng = np.random.default_rng(seed)
    f = _filter(seed) if statics else DriftFilter(DriftFilterParams(), epoch=0.0, start=0.0)
    twin = _filter(seed) if statics else DriftFilter(DriftFilterParams(), epoch=0.0, start=0.0)
    t = 20.0                                              # after _filter's moves (5 to 14 s)
    for what, dt in steps:
        t += dt
        if what == "M":                                   # a measurement (gated or not)
            z = rng.normal(size=2) * 5.0
            S = rng.normal(size=(2, f.statics)) if f.statics else None
            for g in (f, twin):
                g.measure_projected(t, z, np.eye(2), np.eye(2) * 4.0, static=S)
        elif what == "c":                                 # a move that creeps
            step = rng.normal(size=2) * 800.0
            f.record_move(t, step)
            twin.record_move(t, step)
        elif what == "x":                                 # the full offset first, then the mean
            full = f.offset(t + 3.0).offset
            assert np.array_equal(f.offset_mean(t + 3.0), full)
        else:                                             # "o": the mean first, at a time asked again
            mean = f.offset_mean(t + 2.0)
            assert np.array_equal(mean, f.offset(t + 2.0).offset)
            mean[:] = 1e9                                 # a copy
            assert np.array_equal(f.offset_mean(t + 2.0), twin.offset(t + 2.0).offset)
        assert np.array_equal(f.offset_mean(t + 0.5), twin.offset(t + 0.5).offset)


def test_the_filter_refuses_statics_of_the_wrong_shape():
    f = _filter(0)
    with pytest.raises(ValueError, match="statics"):
        f.weigh_many(30.0, np.eye(2), np.eye(2), np.zeros((3, 2, 2)))
    with pytest.raises(ValueError, match="statics"):
        f.weigh_many(30.0, np.eye(2), np.eye(2), np.full((1, 2, f.statics), np.nan))


def test_the_full_scans_row_terms_are_kept_by_row_and_made_again_when_its_moves_change():
    sd = ScanDrift(0.0, 0.1, 0.03, 30.0, creep_std=0.01, tau_std=0.3)
    moves = [(1.0, np.array([2000.0, -500.0])), (40.0, np.array([-300.0, 800.0]))]
    sd.scan_ended(moves[:1])
    J = sd.jacobian(120.0)
    J[:, :] = 7.0                                            # the caller's copy, not the kept one
    m = sd.moves
    assert sd.jacobian(120.0)[:, EPS] == pytest.approx(creep_offset(120.0, m[:, 0], m[:, 1:], 0.03, 30.0))
    assert sd.jacobian(120.0)[:, LAM] == pytest.approx(creep_tau_sensitivity(120.0, m[:, 0], m[:, 1:], 0.03, 30.0))
    before = sd.creep_at(120.0)
    sd.scan_ended(moves)                                     # a second move: the terms change with it
    m = sd.moves
    assert sd.creep_at(120.0) == pytest.approx(creep_offset(120.0, m[:, 0], m[:, 1:], 0.03, 30.0))
    assert not np.allclose(sd.creep_at(120.0), before)
    assert ScanDrift.from_state(sd.state_dict()).jacobian(120.0) == pytest.approx(sd.jacobian(120.0))


def _kalman(objs):
    belief = Belief(Environment((4000.0, 4000.0), tuple(objs), ()), 0.0)
    refs = References.of_scan(objs, belief.seen)
    est = Kalman((0.0, 0.0), 0.0, OPTS)
    est.moved_to((0.0, 0.0), 1.0)
    est.moved_to((3000.0, 0.0), 2.0)
    est.full_scan_done()
    est.restart(0.0)
    return est, belief, refs


def test_the_scan_model_read_from_the_filter_follows_every_change_of_its_state():
    objs = [EnvObject("r1", "particle", (1000.0, 1000.0), 90.0), EnvObject("r2", "particle", (3000.0, 3000.0), 90.0)]
    est, _, refs = _kalman(objs)
    for step in (lambda: None, lambda: est.measure("r1", (1003.0, 998.0), np.eye(2), 30.0, refs, [], set()),
                 lambda: est.moved_to((500.0, 2500.0), 40.0),
                 lambda: est.measure("r2", (3005.0, 3001.0), np.eye(2), 90.0, refs, [], set())):
        step()
        theta, cov = est.scan_theta()
        fresh = filter_theta(est.filter, 4, est.params.creep.amplitude)
        assert theta == pytest.approx(fresh[0], abs=0) and cov == pytest.approx(fresh[1], abs=0)
        theta[:] = 99.0                                           # a copy
        assert est.scan_theta()[0] == pytest.approx(fresh[0], abs=0)


def test_the_reference_choices_batched_terms_are_the_one_by_one_ones():
    rng = np.random.default_rng(3)
    objs = [EnvObject(f"o{k}", "particle", tuple(rng.uniform(300, 3700, 2)), float(rng.uniform(70, 110)))
            for k in range(12)]
    est, belief, refs = _kalman(objs)
    t = 50.0
    est.measure("o0", np.asarray(objs[0].at) + (2.0, -1.0), np.eye(2), 30.0, refs, [], set())
    ctx = RunContext(InstrumentConfig(), OPTS, est, belief, refs, moving={"o1"})
    ctx.observe("o2", (objs[2].at[0] + 1.0, objs[2].at[1]), 40.0, np.eye(2) * 3.0)    # no longer raw
    ctx.here = np.array([100.0, 200.0])
    got = {c.id: c for c in object_candidates(ctx, est, t, 25.0)}
    assert "o1" not in got and {"o2", "o3"} <= set(got) and len(got) >= 9
    for oid, c in got.items():
        tau = refs.first_seen[oid][1] - est.epoch
        assert c.gain == pytest.approx(est.information(t, np.eye(2), est.static_rows(np.eye(2), [tau, tau]), c.R),
                                       rel=1e-9)
        o = belief[oid]
        spacing, margin = ctx.scan_opts.resolved(o.diameter).spacing, ctx.scan_opts.resolved(o.diameter).margin
        length = 2 * (o.radius + ctx.r_max(t, oid) + margin)
        travel = math.dist(ctx.here, ctx.position(oid) + est.offset(t))
        seconds = ctx.timing.seconds(2, 2 * int(length / spacing)) + travel / ctx.config.max_speed + 2 * travel / 1000
        assert c.seconds == pytest.approx(seconds, rel=1e-9)


@pytest.mark.parametrize("made_up", [False, True])
def test_the_reference_chosen_without_weighing_every_candidate_is_the_one_chosen_of_all(monkeypatch, made_up):
    """The real gains lie close together (the nearest candidate wins); made-up ones, each at
    most the offset's variance as a real one is, put the best anywhere in the order."""
    monkeypatch.setattr(reference_choice, "BATCH", 3)            # small batches: most are never weighed
    weighed = []
    terms = reference_choice._terms

    def spy(ctx, est, t, ids, R):
        weighed.append(len(ids))
        cov, gains = terms(ctx, est, t, ids, R)
        trace = np.trace(est.filter.offset(est.clamp(t)).cov)
        assert np.all(gains <= trace)                              # what the bound rests on
        if made_up:
            gains = np.array([trace * (0.02 + 0.98 * (int(oid[1:]) * 7919 % 97) / 96) for oid in ids])
        return cov, gains

    monkeypatch.setattr(reference_choice, "_terms", spy)
    rng = np.random.default_rng(11)
    objs = [EnvObject(f"o{k}", "particle", tuple(rng.uniform(200, 3800, 2)), float(rng.uniform(60, 120)))
            for k in range(40)]
    est, belief, refs = _kalman(objs)
    ctx = RunContext(InstrumentConfig(), OPTS, est, belief, refs, moving={"o1", "o7"})
    pruned = 0
    for k, t in enumerate((20.0, 45.0, 80.0, 200.0, 600.0)):
        if k % 2:
            oid = f"o{3 * k}"
            est.measure(oid, np.asarray(belief[oid].at) + rng.normal(0, 2, 2), np.eye(2), t - 5.0, refs, [], set())
        for here in (None, rng.uniform(0, 4000, 2), rng.uniform(0, 4000, 2)):
            ctx.here = here
            for exclude in ((), ("o4", "o9"), tuple(f"o{j}" for j in range(0, 40, 2))):
                everything = best([c for c in object_candidates(ctx, est, t, 25.0) if c.id not in exclude])
                weighed.clear()
                got = best_object(ctx, est, t, 25.0, exclude)
                assert (got.id, got.rate, got.gain, got.seconds) == (everything.id, everything.rate, everything.gain,
                                                                     everything.seconds)
                pruned += sum(weighed) < 40 - len(exclude) - 2
    assert pruned >= 10                                              # the bound does leave candidates out


points = st.lists(st.tuples(st.floats(0, 400), st.floats(0, 400)), min_size=0, max_size=30)


@settings(max_examples=40, deadline=None)
@given(points, points, st.floats(1.0, 60.0))
def test_slots_keep_the_objects_in_them_as_the_rule_says(slots, objs, tol):
    tolerance = Tolerance(position=tol, size=0.2, angle=5.0)
    layout = Layout((400.0, 400.0), tuple(Body(f"s{k}", "particle", at, 90.0) for k, at in enumerate(slots)),
                    tolerance=tolerance)
    pool = [EnvObject(f"o{k}", "particle", at, 90.0) for k, at in enumerate(objs)]
    got = match(layout, pool, PlanOptions())
    taken, want = set(), []
    for t in layout.targets:                                   # every slot against every object
        inside = sorted((math.dist(o.at, t.at), o.id) for o in pool if o.id not in taken and in_slot(t, o, tolerance))
        if inside:
            want.append((t.id, inside[0][1]))
            taken.add(inside[0][1])
    assert list(got.staying) == want


def test_the_3d_views_resting_heights_follow_the_objects_as_they_move():
    h = np.zeros((60, 60))
    h[20:23, 30:33] = 40.0
    logged = []
    view = SurfaceView(lambda topic, msg, t: logged.append((topic, msg)), lambda t: timestamp(0))
    view(FULL_SCAN, {"t": 1.0, "height": h, "pixel_size": 1.0, "origin": [0, 0]}, 1.0)
    surface = surface_grid(h, 1.0)
    for at in ([10.0, 10.0], [31.5, 21.5], [10.0, 10.0]):
        body = {"id": "p", "at": at, "diameter": 4.0}
        view(CHECKPOINT, {"belief": {"objects": [body], "lost": []}}, 2.0)
        topic, msg = logged[-1]
        assert topic == SURFACE_TOPIC
        assert decoded(msg).entities[0].spheres[0].pose.position.z == pytest.approx(surface.rest(body) + 2.0)


def test_bodies_drawn_from_the_last_checkpoints_parts_are_drawn_as_anew():
    from nanoasm.executor.foxglove_scenes import COLOURS, bodies_scene
    from nanoasm.executor.json_parts import kept

    h = np.zeros((80, 80))
    h[20:26, 30:36] = 40.0
    surface = surface_grid(h, 1.0)
    lifts = []

    def lift(b):
        lifts.append(b["id"])
        return surface.rest(b)

    rng = np.random.default_rng(2)
    parts = {f"o{k}": kept({"id": f"o{k}", "at": list(rng.uniform(5, 75, 2)), "diameter": 4.0}) for k in range(12)}
    parts["r"] = kept({"id": "r", "at": [33.0, 23.0], "diameter": 3.0, "length": 20.0, "angle": 30.0})
    memo, stamp = {}, timestamp(5)
    for step in range(6):
        moved = set(rng.choice(sorted(parts), 3, replace=False)) if step else set(parts)
        if step:                                        # some move (new parts), one becomes a plain dict
            for oid in moved:
                parts[oid] = kept({**parts[oid], "at": list(rng.uniform(5, 75, 2))})
            parts["o0"] = dict(parts["o0"])
        lifts.clear()
        bodies = [*parts.values(), {"id": "bad", "at": None, "diameter": 1.0}]
        got = bodies_scene(bodies, "obj", COLOURS["belief"], stamp, delete=["gone"], lift=lift, memo=memo)
        fresh = bodies_scene(bodies, "obj", COLOURS["belief"], stamp, delete=["gone"], lift=surface.rest)
        assert got == fresh
        assert sorted(lifts) == sorted(moved | ({"o0"} if step else set()))    # the moved and the plain dict
        assert set(memo) == {id(b) for b in parts.values() if type(b) is not dict}


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(0, 2000), st.floats(0, 2000), st.floats(20, 120), st.booleans()), min_size=1,
                max_size=25),
       st.lists(st.tuples(st.integers(0, 40), st.floats(0, 2000), st.floats(0, 2000), st.sampled_from("mad")),
                max_size=15),
       st.tuples(st.floats(0, 2000), st.floats(0, 2000)), st.floats(0, 800))
def test_the_beliefs_index_finds_every_object_within_reach_as_they_move(objs, changes, at, reach):
    from nanoasm.executor.belief import Objects

    def body(k, x, y, d, rod):
        return EnvObject(f"o{k}", "rod" if rod else "particle", (x, y), d, 10.0 if rod else None,
                         6 * d if rod else None)

    objects = Objects((f"o{k}", body(k, *o)) for k, o in enumerate(objs))
    for k, x, y, what in changes:
        objects.near(at, reach)                                   # an index to keep up to date
        oid = f"o{k}"
        if what == "m" and oid in objects:                        # moved, and grown
            o = objects[oid]
            objects[oid] = replace(o, at=(x, y), diameter=o.diameter * 2, length=o.length and o.length * 2)
        elif what == "a":
            objects[oid] = body(k, x, y, 50.0, k % 2 == 0)
        elif what == "d":
            objects.pop(oid, None)
        near = objects.near(at, reach)
        want = [oid for oid, o in objects.items() if math.dist(o.at, at) < reach + (o.length or o.diameter)]
        assert [oid for oid in near if oid in want] == want       # all of them, in order


def test_an_object_that_grows_in_place_is_found_by_the_beliefs_index():
    from nanoasm.executor.belief import Objects

    objects = Objects(o1=EnvObject("o1", "particle", (150.0, 0.0), 40.0),
                      o2=EnvObject("o2", "particle", (900.0, 0.0), 40.0))
    assert objects.near((0.0, 0.0), 100.0) == []
    objects["o1"] = replace(objects["o1"], diameter=80.0)                    # its row kept, its extent larger
    assert objects.near((0.0, 0.0), 100.0) == ["o1"]


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.text("ab1", min_size=1, max_size=40), st.floats(-5e4, 5e4), st.floats(-5e4, 5e4),
                          st.floats(1.0, 500.0),
                          st.one_of(st.none(), st.tuples(st.floats(10, 3000), st.floats(-180, 180)))),
                max_size=12),
       st.lists(st.text("xyz", min_size=1, max_size=5), max_size=3), st.integers(0, 10**15), st.booleans())
def test_a_scene_of_bodies_is_the_encoding_of_its_foxglove_message(bodies, delete, ns, lifted):
    """:func:`bodies_scene`'s bytes (each body's entity encoded once, the stamp put before
    it) are the protobuf encoding of the ``SceneUpdate`` made of ``SceneEntity`` messages,
    whatever the stamp, ids (labels of any length) and deletions."""
    from foxglove.messages import SceneEntity, SceneEntityDeletion, SceneUpdate

    from nanoasm.executor.foxglove_scenes import COLOURS, _shapes, bodies_scene, timestamp

    docs = [{"id": i, "at": [x, y], "diameter": d, **({"length": r[0], "angle": r[1]} if r else {})}
            for i, x, y, d, r in bodies]
    stamp = timestamp(ns)

    def lift(b):
        return 0.5 * b["diameter"] if lifted else 0.0

    entities = []
    for b in docs:
        rod = (float(b["length"]), float(b["angle"])) if "length" in b else ()
        text, shapes = _shapes((COLOURS["belief"], b["id"], *b["at"], b["diameter"], lift(b), *rod))
        entities.append(SceneEntity(timestamp=stamp, frame_id="layout", id=f"obj:{b['id']}", texts=[text], **shapes))
    message = SceneUpdate(entities=entities,
                          deletions=[SceneEntityDeletion(timestamp=stamp, id=f"obj:{i}") for i in delete])
    assert bodies_scene(docs, "obj", COLOURS["belief"], stamp, delete=delete, lift=lift) == message.encode()


@settings(max_examples=80, deadline=None)
@given(st.lists(st.tuples(st.sampled_from([0.0, 10.0, 10.5]), st.sampled_from([0.0, -3.0]),
                          st.sampled_from([80.0, 90.0]), st.sampled_from([None, 0.0, 30.0]), st.sampled_from([300.0, 400.0]),
                          st.sampled_from([0.0, 2.5])), min_size=1, max_size=30))
def test_a_kept_footprint_is_the_footprint_buffered_anew(shapes):
    """The dependency graph's footprints, kept by what makes them, are the footprints
    buffered anew for bodies that differ in any one of centre, diameter, angle, length
    and growth (a key without one of them hands a stale one out)."""
    import shapely

    from nanoasm.planner import sequence

    sequence._FOOTPRINTS.clear()
    for k, (x, y, d, angle, length, grow) in enumerate(shapes):
        b = (Body(f"o{k}", "particle", (x, y), d) if angle is None
             else Body(f"o{k}", "rod", (x, y), d, angle, length))
        fresh = b.geometry().buffer(b.radius + grow, quad_segs=8)
        assert shapely.to_wkb(sequence._footprint(b, grow)) == shapely.to_wkb(fresh)


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 700))
def test_the_kept_moves_handed_out_never_change_as_moves_come_and_freeze(seed, n):
    """The kept moves live in buffers that grow: a move is written after the rows handed
    out, and freezing (slow moves, or the oldest past ``max_moves``) makes new buffers, so
    arrays read earlier keep their values; the arrays are moves recorded, in order."""
    from nanoasm.drift.creep import CreepHistory, CreepModelParams

    rng = np.random.default_rng(seed)
    h = CreepHistory(CreepModelParams(amplitude=0.01, tau=30.0, max_moves=64))
    seen, recorded = [], []
    t = 0.0
    for _ in range(n):
        t += float(rng.exponential(3.0))
        step = rng.normal(size=2) * float(rng.choice([30.0, 800.0]))
        if h.record(t, step):
            recorded.append((t, *step))
        times, steps = h.times, h.steps
        assert not times.flags.writeable and not steps.flags.writeable
        seen.append((times, times.copy(), steps, steps.copy()))
        assert len(h) == times.size <= 64
        rows = np.column_stack([times, steps])
        kept = np.array(recorded) if recorded else np.empty((0, 3))
        assert all(any(np.array_equal(r, k) for k in kept) for r in rows)     # recorded moves, ...
        assert np.all(np.diff(times) >= 0)                                     # ... in order
    for view, copy, sview, scopy in seen:
        assert np.array_equal(view, copy) and np.array_equal(sview, scopy)


def _same(a, b) -> bool:
    """Two geometries of one type with the same coordinates to the bit."""
    import shapely

    return a.geom_type == b.geom_type and np.array_equal(shapely.get_coordinates(a), shapely.get_coordinates(b))


_BODY = st.tuples(st.floats(-5e4, 5e4), st.floats(-5e4, 5e4), st.floats(0.5, 400.0),
                  st.one_of(st.none(), st.tuples(st.floats(1.0, 8.0), st.floats(-360, 360))))


def _bodies(specs) -> list[Body]:
    return [Body(f"o{k}", "particle", (x, y), d) if rod is None else
            Body(f"o{k}", "rod", (x, y), d, rod[1], d * rod[0]) for k, (x, y, d, rod) in enumerate(specs)]


@settings(max_examples=60, deadline=None)
@given(st.lists(_BODY, max_size=20))
def test_the_cores_made_at_once_are_each_bodys_own_geometry(specs):
    from nanoasm.bodies import geometries

    bodies = _bodies(specs)
    got = geometries(bodies)
    assert got.shape == (len(bodies),)
    assert all(_same(g, b.geometry()) for g, b in zip(got, bodies))


@settings(max_examples=60, deadline=None)
@given(st.lists(_BODY, max_size=20), st.sampled_from([0.0, 7.5, 31.25]), st.integers(0, 2))
def test_the_footprints_made_at_once_are_the_buffers_to_the_bit(specs, grow, kept):
    """The dependency graph's footprints, the discs made from the unit circle in one call,
    are the polygons ``buffer`` makes, whatever was kept from before (none, some, all,
    of another size)."""
    from nanoasm.planner import sequence

    bodies = _bodies(specs)
    sequence._FOOTPRINTS.clear()
    sequence._footprints(bodies[: len(bodies) * kept // 2], grow)
    sequence._footprints(bodies, 3.0 + grow)                 # kept, each of another size
    for g, b in zip(sequence._footprints(bodies, grow), bodies):
        assert _same(g, b.geometry().buffer(b.radius + grow, quad_segs=8))
    sequence._FOOTPRINTS.clear()


@pytest.mark.parametrize("state", ["bootstrap", "filter", "measured", "jumped"])
def test_the_beliefs_positions_at_once_are_each_ones_own_to_the_bit(state):
    """:meth:`RunContext.environment` and :meth:`RunContext.positions` put every object seen
    only in the full scan back by its row's drift in one product: each position to the bit
    the one :meth:`RunContext.position` gives alone, and the environment the one made with
    ``dataclasses.replace`` object by object (given-up objects without confidence, lost
    ones left out), in every state of the drift estimate."""
    from nanoasm.executor.belief import Seen

    rng = np.random.default_rng(5)
    objs = [EnvObject(f"o{k}", "particle", tuple(rng.uniform(300, 3700, 2)), float(rng.uniform(70, 110)))
            for k in range(30)]
    objs.append(EnvObject("r", "rod", (2000.0, 2100.0), 40.0, 30.0, 400.0))
    belief = Belief(Environment((4000.0, 4000.0), tuple(objs), ()), 0.0)
    for k, o in enumerate(objs):                                  # each row its own time
        belief.seen[o.id] = Seen(float(rng.uniform(100.0, 600.0)), np.eye(2) * 4.0)
    refs = References.of_scan(objs, belief.seen)
    est = Kalman((0.0, 0.0), 100.0, OPTS)
    est.moved_to((0.0, 0.0), 101.0)
    est.moved_to((3000.0, 0.0), 102.0)
    est.full_scan_done(610.0)
    if state != "bootstrap":
        est.restart(620.0)
    if state in ("measured", "jumped"):
        est.measure("o0", np.asarray(objs[0].at) + (3.0, -2.0), np.eye(2), 660.0, refs, [], set())
    if state == "jumped":
        est.scan.stepped, est.scan.tau_jump, est.scan.jump = True, 250.0, np.array([180.0, -75.0])
    ctx = RunContext(InstrumentConfig(), OPTS, est, belief, refs)
    ctx.observe("o2", (objs[2].at[0] + 1.0, objs[2].at[1]), 670.0, np.eye(2) * 3.0)    # no longer raw
    belief.lose("o3")
    ctx.ledger.given_up.add("o4")
    ids = list(belief.objects)
    one = np.array([ctx.position(i) for i in ids])
    assert np.array_equal(ctx.positions(ids), one)
    assert np.array_equal(ctx.positions(ids[::-1]), one[::-1])
    assert ctx.positions([]).shape == (0, 2)
    want = []
    for o in belief.objects.values():
        if o.id in belief.lost:
            continue
        if o.id in refs.raw:
            o = replace(o, at=tuple(float(v) for v in ctx.position(o.id)))
        want.append(replace(o, confidence=0.0) if o.id == "o4" else o)
    got = ctx.environment().objects
    assert [(o.id, o.at, o.confidence) for o in got] == [(o.id, o.at, o.confidence) for o in want]
    assert got == tuple(want) and "o3" not in {o.id for o in got}
    assert any(o.at != b.at for o, b in zip(got, objs))           # the rows' drift did move them


def test_an_objects_new_pose_or_confidence_is_checked_as_a_new_object_is():
    o = EnvObject("o1", "rod", (1.0, 2.0), 40.0, 30.0, 400.0, 0.7, True)
    for change in (dict(at=(5.0, 6.0)), dict(confidence=0.0), dict(at=(-3.0, 1e5), confidence=1.0)):
        assert o.changed(**change) == replace(o, **change)
    assert o == EnvObject("o1", "rod", (1.0, 2.0), 40.0, 30.0, 400.0, 0.7, True)       # itself unchanged
    for bad in (dict(at=(math.nan, 0.0)), dict(at=(1.0,)), dict(at=(0.0, math.inf)), dict(confidence=1.5),
                dict(confidence=-0.1)):
        with pytest.raises(ValueError) as mine:
            o.changed(**bad)
        with pytest.raises(ValueError) as theirs:
            replace(o, **bad)
        assert str(mine.value) == str(theirs.value)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.sampled_from([None, 0.5, 2.0]), st.sampled_from([None, 0.0, 30.0]),
                          st.sampled_from([None, 12.0]), st.floats(1.0, 500.0)), min_size=1, max_size=12))
def test_scan_options_resolved_again_are_those_made_anew(asks):
    """:meth:`ScanOptions.resolved`, kept by options and diameter, is what filling in the
    defaults anew gives, whichever options and diameters were asked before."""
    from nanoasm.executor.scan_lines import ScanOptions

    for spacing, margin, height, d in asks + asks[::-1]:
        opts = ScanOptions(spacing=spacing, margin=margin, height=height)
        sp = spacing if spacing is not None else min(1.0, d / 20)
        want = replace(opts, spacing=sp, margin=margin if margin is not None else d / 2 + 10 * sp,
                       height=height if height is not None else d)
        got = opts.resolved(d)
        assert got == want and type(got.height) is float
    with pytest.raises(Exception, match="diameter"):
        ScanOptions().resolved(float("nan"))


def test_the_courses_starts_in_a_checkpoint_are_their_json_as_they_change():
    """The course's starts are encoded once while they stand (the same kept part from one
    checkpoint to the next) and anew after every :meth:`Course.follow`, extending or not:
    the checkpoint's JSON is always that of the starts as they are."""
    import json

    from nanoasm.executor import json_parts
    from nanoasm.executor.course import Course
    from nanoasm.planner import Expect, Operation

    def ops(first, n, x):
        return [Operation(first + k, f"o{k % 3}", None, ((x, 0.0), (x + 10.0, 0.0)), Expect((x + 10.0 * k, 1.0), None))
                for k in range(n)]

    env = Environment((4000.0, 4000.0), tuple(EnvObject(f"o{k}", "particle", (100.0 * k, 50.0), 80.0)
                                             for k in range(3)), ())
    course = Course()
    for step, (first, n, x, extend) in enumerate([(1, 4, 5.0, False), (5, 2, 7.5, True), (1, 3, 9.0, False),
                                                  (4, 1, 2.0, True)]):
        course.follow(env, ops(first, n, x), extend=extend)
        course.slipped(f"o{step % 3}")
        one, two = course.state_dict(), course.state_dict()
        assert one["plan_start"] is two["plan_start"]                     # kept while the starts stand
        plain = {"plan_start": {str(k): [list(at), ang] for k, (at, ang) in course.starts.items()},
                 "preload_factor": dict(course.preload)}
        assert json_parts.dumps({"course": one}) == json.dumps({"course": plain}, separators=(",", ":"))
        assert json_parts.dumps(json_parts.PartsDict(course=two)) == json.dumps({"course": plain},
                                                                                separators=(",", ":"))
        assert Course.from_state(json.loads(json_parts.dumps(one))) == course
