"""What a 1000-object run keeps or does at once instead of one by one (issue 16) gives what
the one-by-one way gives: the filter's projections of many candidates, the full scan's
row terms kept by row, the scan model read from the filter while its state stands, the
reference choice's batched terms, the slot-filled test through a k-d tree, and the 3-D
view's resting heights."""

from __future__ import annotations

import math

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
from nanoasm.executor.reference_choice import object_candidates
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
