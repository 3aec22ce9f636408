"""Pushes of several particles in one contact phase (executor/batching.py, issue 16)."""

from __future__ import annotations

import numpy as np
import pytest

from nanoasm.executor.batching import together
from nanoasm.executor.belief import Belief
from nanoasm.executor.context import RunContext
from nanoasm.executor.estimators import Kalman
from nanoasm.executor.references import References
from nanoasm.executor.strategy import ExecOptions
from nanoasm.instrument import InstrumentConfig
from nanoasm.planner import Expect, Operation
from nanoasm.world.environment import EnvObject, Environment


def _ctx(objects, **options) -> RunContext:
    env = Environment((20000.0, 20000.0), tuple(objects), ())
    belief = Belief(env, 0.0)
    for o in objects:                      # seen by scans since: no row drift to put back
        belief.observe(o.id, o.at, 1.0, [[1.0, 0.0], [0.0, 1.0]])
    refs = References.of_scan(list(objects), belief.seen)
    est = Kalman((0.0, 0.0), 0.0, ExecOptions())
    opts = ExecOptions(strategy="full", **options)
    return RunContext(InstrumentConfig(), opts, est, belief, refs, moving={o.id for o in objects})


def _p(oid, x, y) -> EnvObject:
    return EnvObject(oid, "particle", (float(x), float(y)), 90.0)


def _push(k, o: EnvObject, dx, dy=0.0) -> Operation:
    """A push of ``o`` by (dx, dy): the tip from behind it to where it should stop."""
    x, y = o.at
    n = (dx * dx + dy * dy) ** 0.5
    ux, uy = dx / n, dy / n
    back = 45.0 + 5.0 + 10.0
    return Operation(k, o.id, None, ((x - back * ux, y - back * uy), (x + dx - 50.0 * ux, y + dy - 50.0 * uy)),
                     Expect((x + dx, y + dy)))


def _ids(ops):
    return [(op.id, op.object) for op in ops]


FAR = [_p("a", 2000, 2000), _p("b", 8000, 2000), _p("c", 2000, 8000), _p("d", 8000, 8000)]


def test_pushes_far_apart_go_together_up_to_the_limit_and_each_objects_first_push_only():
    a, b, c, d = FAR
    ops = [_push(0, a, 500), _push(1, a, 500), _push(2, b, 500), _push(3, b, 500), _push(4, c, 500),
           _push(5, d, 500)]
    ctx = _ctx(FAR, contact_batch=3)
    n = together(ctx, ops, 0, _plan_options())
    assert n == 3
    # b's and c's first pushes brought forward over a's second; every push kept, in order otherwise
    assert _ids(ops) == [(0, "a"), (2, "b"), (4, "c"), (1, "a"), (3, "b"), (5, "d")]
    assert together(ctx, ops, 3, _plan_options()) == 3       # a's second, b's second, d's
    assert _ids(ops[3:]) == [(1, "a"), (3, "b"), (5, "d")]


def _plan_options():
    from nanoasm.planner import PlanOptions
    return PlanOptions()


@pytest.mark.parametrize("limit", [1, 2])
def test_the_limit_holds_and_one_leaves_the_plan_as_it_is(limit):
    a, b, c, d = FAR
    ops = [_push(0, a, 500), _push(1, b, 500), _push(2, c, 500)]
    before = list(ops)
    assert together(_ctx(FAR, contact_batch=limit), ops, 0, _plan_options()) == limit
    assert ops == before


def test_a_push_near_another_ones_sweep_waits_for_it():
    """b lies where a's push ends (the plan pushes b after a: b clears a's slot, or a's
    push would shove it): never brought forward; nor is a push within replan_after of an
    area it would jump over, nor a rod."""
    a = _p("a", 2000, 2000)
    b = _p("b", 2650, 2000)          # its push starts 35 nm from where a's ends: within 60
    c = _p("c", 2000, 8000)
    rod = EnvObject("r", "rod", (8000.0, 8000.0), 60.0, 0.0, 600.0)
    objs = [a, b, c, rod]
    ops = [_push(0, a, 500), _push(1, b, 500), _push(2, rod, 0.0, 500), _push(3, c, 500)]
    ctx = _ctx(objs, contact_batch=4)
    assert together(ctx, ops, 0, _plan_options()) == 2
    assert _ids(ops) == [(0, "a"), (3, "c"), (1, "b"), (2, "r")]
    # the margin is replan_after: at 20 nm b goes with a
    ops = [_push(0, a, 500), _push(1, b, 500)]
    assert together(_ctx(objs, contact_batch=4, replan_after=20.0), ops, 0, _plan_options()) == 2
    # a rod's push leads no group
    ops = [_push(2, rod, 0.0, 500), _push(3, c, 500)]
    assert together(ctx, ops, 0, _plan_options()) == 1


def test_a_push_whose_area_crosses_a_later_push_of_another_object_is_not_brought_over_it():
    a, b = _p("a", 2000, 2000), _p("b", 6000, 2000)
    c = _p("c", 3000, 2600)                  # its push crosses the way b's second push goes
    objs = [a, b, c]
    ops = [_push(0, a, 300), _push(1, b, 300), _push(2, b, -3000, 0.0), _push(3, c, 0.0, -1200)]
    ctx = _ctx(objs, contact_batch=4)
    assert together(ctx, ops, 0, _plan_options()) == 2          # a with b; c waits for b's second
    assert _ids(ops) == [(0, "a"), (1, "b"), (2, "b"), (3, "c")]


def test_lost_objects_do_not_join():
    a, b, c, d = FAR
    ctx = _ctx(FAR, contact_batch=4)
    ctx.belief.lose("b")
    ops = [_push(0, a, 500), _push(1, b, 500), _push(2, c, 500)]
    assert together(ctx, ops, 0, _plan_options()) == 2
    assert _ids(ops) == [(0, "a"), (2, "c"), (1, "b")]


def test_without_scans_nothing_is_grouped():
    a, b, c, d = FAR
    ctx = _ctx(FAR, contact_batch=4)
    ctx.options = ExecOptions(strategy="open-loop", contact_batch=4)
    ops = [_push(0, a, 500), _push(1, b, 500)]
    assert together(ctx, ops, 0, _plan_options()) == 1


def _corner_scene():
    """Four particles near the corners of a 6 µm area, each pushed 600 nm to a slot
    beside it: no push can touch another's."""
    from nanoasm.cad.layout import layout_from_dict
    from nanoasm.world.scene import scene_from_dict

    corners = [(1200, 1200), (4800, 1200), (1200, 4800), (4800, 4800)]
    scene = scene_from_dict({"format": "nanoasm.scene/1", "area": [6000, 6000], "seed": 5, "object": [
        {"id": f"p{k}", "kind": "particle", "at": [x, y], "diameter": 90} for k, (x, y) in enumerate(corners)]})
    layout = layout_from_dict({"format": "nanoasm.layout/1", "area": [6000, 6000], "target": [
        {"id": f"s{k}", "kind": "particle", "at": [x + (600 if x < 3000 else -600), y], "diameter": 90}
        for k, (x, y) in enumerate(corners)]})
    return scene, layout


def test_a_dry_run_in_groups_switches_less_and_its_verdict_is_the_truth():
    """Each group's pushes are made between one switch into contact and one back: fewer
    mode switches than one push at a time, every slot truly filled, the run's own verdict
    the truth's."""
    from nanoasm.dryrun import dry_run

    scene, layout = _corner_scene()
    runs = {}
    for batch in (1, 4):
        events = []
        out = dry_run(scene, layout, seed=5, options=ExecOptions(contact_batch=batch),
                      subscribers=[lambda topic, doc: events.append(doc) if topic == "event" else None])
        runs[batch] = out, [e.text for e in events if "contact phase" in e.text]
    (one, none), (grouped, groups) = runs[1], runs[4]
    assert not none and groups
    for out in (one, grouped):
        assert out.truly_filled == ("s0", "s1", "s2", "s3") and not out.disagreements
    assert grouped.report.instrument_time.mode_switch < one.report.instrument_time.mode_switch


class _Est:
    """A drift estimate whose offset is ``x + v t``; a measurement moves ``x`` by ``jump``."""

    def __init__(self):
        self.x, self.v, self.jump, self.time = np.zeros(2), np.array([0.5, 0.0]), np.array([2.0, -1.0]), 0.0
        self.dv = np.array([0.1, 0.0])

    def clamp(self, t):
        return max(t, self.time)

    def offset(self, t):
        return self.x + self.v * t

    def measure(self, obj_id, at, cov, t, refs, pushed, lost, creep_sens=None):
        self.x, self.time, self.v = self.x + self.jump, t, self.v + self.dv      # a velocity revised too
        return True

    def measure_feature(self, feature_id, z, H, R, t, taus=None, creep_sens=None):
        return self.measure(feature_id, z, R, t, None, (), ())

    def sigma(self, t):
        return 3.0


def test_each_measurement_adds_what_it_moved_the_offset_by_at_its_own_time():
    from nanoasm.executor.batching import _Revisions

    est = _Est()
    watch = _Revisions(est)
    assert watch.sigma(1.0) == 3.0 and watch.offset(2.0).tolist() == [1.0, 0.0]     # the rest as it is
    assert watch.measure("a", (0, 0), np.eye(2), 10.0, None, (), ()) is True
    # new less old at t = 10: the jump and the velocity's revision over 10 s
    assert watch.shift == pytest.approx([2.0 + 1.0, -1.0])
    watch.measure_feature("f", (0, 0), np.eye(2), np.eye(2), t=4.0)                 # before the filter: at 10
    assert watch.shift == pytest.approx([3.0 + 3.0, -2.0])


def test_a_prepared_particle_follows_the_estimates_shift_back_and_a_lost_one_stays():
    from nanoasm.executor.batching import _follow

    a, b, c, d = FAR
    ctx = _ctx(FAR)
    ctx.belief.lose("b")
    _follow(ctx, "a", np.array([3.0, -2.0]))
    _follow(ctx, "b", np.array([3.0, -2.0]))
    _follow(ctx, "c", np.zeros(2))
    assert ctx.belief["a"].at == (1997.0, 2002.0)
    assert ctx.belief["b"].at == b.at and ctx.belief["c"].at == c.at


def test_a_group_aims_each_push_from_its_scan_moved_by_the_revisions_made_after_it(monkeypatch):
    """Member k's scan is followed by the folds of the scans after it (and a failed push's
    drift check before its own push): its belief is moved back by those shifts, not by
    the ones before its scan, just before it is aimed."""
    import nanoasm.executor.batching as batching

    a, b, c, d = FAR
    ctx = _ctx(FAR, contact_batch=3)
    ctx.drift = _Est()
    ctx.drift.v, ctx.drift.dv = np.zeros(2), np.zeros(2)
    jumps = {"a": [1.0, 0.0], "b": [0.0, 2.0], "c": [4.0, 0.0]}
    aimed = {}

    def prepare(ctx_, op, plan_options, trust=True):
        ctx_.drift.jump = np.array(jumps[op.object])      # set through the group's view, on the estimator
        ctx_.drift.measure(op.object, (0, 0), np.eye(2), 1.0, None, (), ())     # its own fold, then its scan
        return None
        yield

    def aim(ctx_, op, course, plan_options):
        aimed[op.object] = ctx_.belief[op.object].at
        return op, ctx_.belief[op.object]

    def press(ctx_, op, start, *rest):
        return "failed"
        yield

    monkeypatch.setattr(batching, "prepare", prepare)
    monkeypatch.setattr(batching, "aim", aim)
    monkeypatch.setattr(batching, "press", press)
    ops = [_push(0, a, 500), _push(1, b, 500), _push(2, c, 500)]
    gen = batching.push_together(ctx, ops, None, None, _plan_options())
    try:
        msg = next(gen)
        while True:
            msg = gen.send(None)
    except StopIteration as stop:
        assert stop.value == ["failed"] * 3
    assert msg.command == "event" and "3 pushes in one contact phase" in msg.args[0]
    assert aimed["a"] == (2000.0 - 4.0, 2000.0 - 2.0)        # b's and c's folds came after a's scan
    assert aimed["b"] == (8000.0 - 4.0, 2000.0)              # c's after b's
    assert aimed["c"] == (2000.0, 8000.0)                    # none after c's
    assert isinstance(ctx.drift, _Est)                        # the estimator itself again


def _drive(gen):
    """Run a plan stub that only emits events: (its value, the event texts)."""
    texts = []
    try:
        msg = next(gen)
        while True:
            texts.append(msg.args[0])
            msg = gen.send(None)
    except StopIteration as stop:
        return stop.value, texts


def test_a_push_a_relocalisation_put_an_object_in_the_way_of_waits_once():
    """``pushing.deferred``: after a relocalisation (``ctx.corrected``) a push whose particle
    would meet another believed one on its way waits for a replan, once an object; a clear
    way, no relocalisation, or the other object pushed in the same group, does not wait."""
    from nanoasm.executor.pushing import deferred

    a, b, c = _p("a", 2000, 2000), _p("b", 2600, 2000), _p("c", 2000, 2600)
    ctx = _ctx([a, b, c])
    through, short = _push(0, a, 900), _push(1, a, 400)       # a's way to x = 2900 or 2400
    assert _drive(deferred(ctx, False, [through])) == (False, [])        # nothing relocalised
    ctx.corrected = True
    assert _drive(deferred(ctx, True, [through])) == (False, [])         # moved before it was prepared
    assert _drive(deferred(ctx, False, [short]))[0] is False             # 2400 + 45: b's edge is at 2555
    assert _drive(deferred(ctx, False, [through, _push(2, b, 0, 900)]))[0] is False   # b goes too
    waits, texts = _drive(deferred(ctx, False, [through]))
    assert waits and "put b in the way of a's push" in texts[0]
    assert _drive(deferred(ctx, False, [through]))[0] is False           # once
