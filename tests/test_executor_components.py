"""The executor's components, each alone, without a dry-run: the drift estimators, the
ledger, the full scan's references, the course, and the scan and motion steps driven by
a fake instrument."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, strategies as st

from nanoasm.bodies import Body
from nanoasm.executor.belief import Belief
from nanoasm.executor.context import RunContext
from nanoasm.executor.course import Course, course_clear, starts
from nanoasm.executor.engine import Msg
from nanoasm.executor.estimators import (
    Anchor,
    Kalman,
    NoDrift,
    estimator_for,
    estimator_from_state,
)
from nanoasm.executor.ledger import RunLedger
from nanoasm.executor.motion_steps import stream_push, travel_to
from nanoasm.executor.reference_choice import LineTiming
from nanoasm.executor.references import References
from nanoasm.executor.scan_steps import run_pattern, scan_line
from nanoasm.executor.strategy import ExecOptions, Strategy
from nanoasm.instrument import InstrumentConfig, SignalBlock
from nanoasm.planner import Operation
from nanoasm.planner.plan import Plan
from nanoasm.world.environment import EnvObject, Environment

OPTS = ExecOptions()


def _env(*objs) -> Environment:
    return Environment((4000.0, 4000.0), tuple(objs), ())


def _particle(oid, x, y, d=90.0) -> EnvObject:
    return EnvObject(oid, "particle", (x, y), d)


# -- drift estimators ---------------------------------------------------------------------
@pytest.mark.parametrize("strategy,kind", [("open-loop", NoDrift), ("local-scan", NoDrift),
                                           ("anchor", Anchor), ("kalman", Kalman), ("full", Kalman)])
def test_each_strategy_picks_its_estimator(strategy, kind):
    est = estimator_for(Strategy(strategy), (100.0, 200.0), 5.0, OPTS)
    assert type(est) is kind
    assert est.offset(5.0) == pytest.approx([100.0, 200.0])


def test_no_drift_grows_its_error_radius_with_the_time_since_a_sighting():
    est = NoDrift((0.0, 0.0), 0.0)
    belief = Belief(_env(_particle("a", 1000, 1000)), 0.0)
    seen = belief.seen["a"]
    r0 = est.radius(0.0, seen, None, OPTS)
    r1 = est.radius(100.0, seen, None, OPTS)
    assert r0 == pytest.approx(OPTS.r_max)
    assert r1 - r0 == pytest.approx(100.0 * OPTS.max_drift_rate)
    assert est.offset(1e6) == pytest.approx([0.0, 0.0])          # nothing is estimated
    assert est.measure("a", (5.0, 5.0), np.eye(2), 1.0, References(), [], set()) is None


def test_the_anchor_gives_the_offset_where_it_is_found_less_where_it_was():
    belief = Belief(_env(_particle("mover", 500, 500), _particle("near", 2100, 2000),
                         _particle("far", 3500, 3500)), 0.0)
    op = Operation(0, "mover", None, ((400.0, 500.0), (900.0, 500.0)),
                   Body("mover", "particle", (1000.0, 500.0), 90.0))
    est = Anchor((10.0, 20.0), 0.0)
    est.after_plan(Plan("x", (), (op,), ()), belief, (4000.0, 4000.0))
    assert est.anchor[0] == "near"                               # unmoved, nearest the centre
    assert est.reference_target(None, 0.0, (0, 0), "mover").id == "near"
    assert est.measure("near", (0.0, 0.0), np.eye(2), 9.0, References(), [], set()) is None   # only its own scan
    assert est.measure_reference("near", (2100.0 + 10 + 7, 2000.0 + 20 - 3), np.eye(2), 9.0, References(), [], set())
    assert est.offset(9.0) == pytest.approx([10.0 + 7, 20.0 - 3])
    assert est.measure_reference("far", (0.0, 0.0), np.eye(2), 9.0, References(), [], set()) is None
    back = estimator_from_state(est.state_dict(), OPTS)
    assert type(back) is Anchor and back.anchor == est.anchor
    assert back.offset(9.0) == pytest.approx(est.offset(9.0))


def _kalman_setup():
    objs = [_particle("r1", 1000, 1000), _particle("r2", 3000, 3000), _particle("p", 2000, 2000)]
    belief = Belief(_env(*objs), 0.0)
    refs = References.of_scan(objs, belief.seen)
    est = Kalman((0.0, 0.0), 0.0, OPTS)
    est.full_scan_done()
    est.restart(0.0)                  # no bootstrap: the filter starts from the drift model's prior
    return est, belief, refs


def test_kalman_folds_a_reference_in_and_gates_out_one_that_moved_on_its_own():
    est, belief, refs = _kalman_setup()
    assert est.measure("r1", (1000.0 + 2.0, 1000.0 - 1.0), np.eye(2), 10.0, refs, [], set()) is True
    off = est.offset(10.0)
    assert 0.0 < off[0] <= 2.0 and -1.0 <= off[1] < 0.0          # pulled toward the measured offset
    assert est.measure("p", (2000.0, 2000.0), np.eye(2), 11.0, refs, ["p"], set()) is None  # pushed
    assert est.measure("r2", (3000.0 + 900.0, 3000.0), np.eye(2), 12.0, refs, [], set()) is False
    assert "r2" in refs.gated and not refs.is_reference("r2", [], set())


def test_kalman_records_only_moves_long_enough_to_creep_and_keeps_the_rest_for_the_next():
    est, _, _ = _kalman_setup()
    small = est.params.creep.min_step / 4
    est.moved_to((0.0, 0.0), 1.0)
    est.moved_to((small, 0.0), 2.0)
    assert est.move_log == []
    est.moved_to((4 * small, 0.0), 3.0)                          # the small step is carried on
    assert len(est.move_log) == 1 and est.move_log[0][1] == pytest.approx([4 * small, 0.0])


def test_kalman_picks_the_reference_of_most_information_per_second_never_a_quarantined_one():
    est, belief, refs = _kalman_setup()
    ctx = RunContext(InstrumentConfig(), OPTS, est, belief, refs, moving={"p"})
    ctx.here = np.array([1000.0, 1000.0])
    assert est.reference_target(ctx, 0.0, (1100.0, 1000.0), "p").id == "r1"   # the nearer: less travel
    refs.quarantine["r1"] = "p"                                    # a push came near it
    assert est.reference_target(ctx, 0.0, (1100.0, 1000.0), "p").id == "r2"
    refs.quarantine["r2"] = "p"
    assert est.reference_target(ctx, 0.0, (1100.0, 1000.0), "p") is None     # "p" moves: none left


def test_kalman_goes_on_from_its_state_as_it_was():
    est, _, refs = _kalman_setup()
    est.moved_to((0.0, 0.0), 1.0)
    est.moved_to((2000.0, 0.0), 2.0)
    est.measure("r1", (1003.0, 998.0), np.eye(2), 30.0, refs, [], set())
    back = estimator_from_state(est.state_dict(), OPTS)
    assert type(back) is Kalman
    for t in (30.0, 60.0, 600.0):
        assert back.offset(t) == pytest.approx(est.offset(t), abs=1e-9)
        assert back.radius(t, None, None, OPTS) == pytest.approx(est.radius(t, None, None, OPTS))


def test_an_unknown_estimator_state_is_refused():
    with pytest.raises(ValueError, match="unknown drift estimator"):
        estimator_from_state({"kind": "magic"}, OPTS)


# -- ledger, references, course -----------------------------------------------------------
def test_the_ledger_gives_up_on_an_object_at_max_failures_and_round_trips():
    led = RunLedger()
    assert [led.trouble("a", 3) for _ in range(3)] == [False, False, True]
    assert led.given_up == {"a"} and led.troubles == {"a": 3}
    led.fail("a", "slipped")
    led.pushed_once("a")
    led.pushed_once("a")
    led.counts["pushes"] += 2
    led.times["push"] += 1.5
    led.drift.append((1.0, 2.0, 3.0))
    back = RunLedger.from_state(led.state_dict())
    assert back == led and back.count().pushes == 2


def test_references_are_objects_never_pushed_gated_or_lost():
    objs = [_particle("a", 10, 10), _particle("b", 20, 20)]
    refs = References.of_scan(objs, Belief(_env(*objs), 3.0).seen)
    assert refs.is_reference("a", [], set())
    assert not refs.is_reference("a", ["a"], set())
    assert not refs.is_reference("a", [], {"a"})
    assert not refs.is_reference("zzz", [], set())
    refs.gated.add("b")
    back = References.from_state(refs.state_dict())
    assert back.raw == refs.raw and back.gated == {"b"}
    assert back.first_seen["a"][0] == pytest.approx([10.0, 10.0]) and back.first_seen["a"][1] == 3.0


def _op(i, obj, frm, to):
    return Operation(i, obj, None, (frm, to), Body(obj, "particle", to, 90.0))


def test_the_course_chains_expected_starts_and_caps_the_raised_preload():
    env = _env(_particle("a", 100, 100))
    ops = [_op(0, "a", (0.0, 100.0), (200.0, 100.0)), _op(1, "a", (200.0, 100.0), (300.0, 100.0))]
    assert starts(env, ops) == {0: ((100, 100), None), 1: ((200.0, 100.0), None)}
    course = Course()
    course.follow(env, ops)
    for _ in range(10):
        course.slipped("a")
    assert course.preload["a"] == 4.0
    back = Course.from_state(course.state_dict())
    assert back.preload == course.preload and set(back.starts) == {0, 1}


def test_a_rods_course_that_would_touch_a_neighbour_is_not_clear():
    rod = Body("r", "rod", (1000.0, 1000.0), 60.0, 0.0, 500.0)
    ahead = [Operation(7, "r", None, ((1000.0, 900.0), (1000.0, 960.0)),
                       Body("r", "rod", (1000.0, 1100.0), 60.0, 0.0, 500.0))]
    plan_starts = {7: ((1000.0, 1000.0), 0.0)}
    far = Body("n", "particle", (1000.0, 1600.0), 90.0)
    near = Body("n", "particle", (1000.0, 1170.0), 90.0)    # 70 nm from the axis: < 45 + 30 + 10
    assert course_clear(rod, plan_starts, ahead, [far], 10.0)
    assert not course_clear(rod, plan_starts, ahead, [near], 10.0)


# -- steps against a fake instrument ------------------------------------------------------
class FakeInstrument:
    """Answers a step's messages: a clock that advances with writes and lines, a flat
    sample with one 50 nm bump at ``bump``; records what it was asked."""

    def __init__(self, config: InstrumentConfig, bump=(45000.0, 45000.0)):
        self.config, self.bump = config, np.asarray(bump)
        self.t, self.codes = 0.0, config.nm_to_codes(np.array([45000.0, 45000.0, config.lift]))
        self.lines: list[tuple] = []
        self.emitted: list[tuple] = []

    def __call__(self, msg: Msg):
        c = msg.command
        if c == "clock":
            return self.t
        if c == "position":
            return self.codes
        if c == "write":
            path = msg.args[0]
            n = len(path)
            ts = self.t + np.arange(1, n + 1) / self.config.sample_rate
            self.t, self.codes = float(ts[-1]), path[-1]
            return SignalBlock(ts, np.zeros(n), np.zeros(n))
        if c == "scan_line":
            a, b, n = msg.args
            self.lines.append((a, b, n))
            pts = np.asarray(a)[None] + np.linspace(0, 1, n)[:, None] * (np.asarray(b) - np.asarray(a))[None]
            self.t += 0.01 * n
            return 50.0 * np.exp(-np.sum((pts - self.bump) ** 2, axis=1) / (2 * 30.0 ** 2))
        if c == "emit":
            self.emitted.append(msg.args)
        return None


def drive(gen, fake):
    """Run a step to its end against ``fake``; its return value."""
    reply = None
    while True:
        try:
            reply = fake(gen.send(reply))
        except StopIteration as stop:
            return stop.value


def _ctx(strategy="kalman"):
    cfg = InstrumentConfig()
    belief = Belief(_env(_particle("a", 1000, 1000)), 0.0)
    drift = estimator_for(Strategy(strategy), (44000.0, 44000.0), 0.0, OPTS)
    return RunContext(cfg, ExecOptions(strategy=strategy), drift, belief, References()), FakeInstrument(cfg)


def test_travel_is_timed_as_travel_and_told_to_the_creep_model():
    ctx, fake = _ctx()
    drive(travel_to(ctx, (47000.0, 45000.0)), fake)
    assert ctx.ledger.times["travel"] == pytest.approx(fake.t)
    # creep follows the travel (40 ms) as it goes, a piece once min_step is reached, and
    # the rest where it ends
    steps = np.array([s for _, s in ctx.drift.move_log])
    times = [t for t, _ in ctx.drift.move_log]
    assert len(steps) == 2 and ctx.drift.params.creep.min_step <= steps[0, 0] < 600.0
    assert steps[:, 0].sum() == pytest.approx(2000.0, abs=2.0) and np.allclose(steps[:, 1], 0.0)
    assert times[0] < times[1] == pytest.approx(fake.t, abs=2e-3)


class SwitchingInstrument(FakeInstrument):
    """The fake instrument, with the switch into contact the simulator makes: a write that
    touches down after scanning waits ``switch`` seconds before its first sample."""

    def __init__(self, config, switch=2.0):
        super().__init__(config)
        self.switch, self.tapping, self.writes = switch, True, []

    def __call__(self, msg: Msg):
        if msg.command == "scan_line":
            self.tapping = True
        if msg.command == "write":
            contact = bool((self.config.codes_to_nm(np.asarray(msg.args[0]))[:, 2] <= 0.0).any())
            if contact and self.tapping:
                self.t += self.switch
                self.tapping = False
            block = super().__call__(msg)
            self.writes.append((contact, float(block.t[0])))
            return block
        return super().__call__(msg)


def test_a_push_after_scanning_is_timed_from_the_switch_into_contact(monkeypatch):
    """The first push after a scan line learns what the switch into contact takes; the next
    one travels to its start lifted, then writes the push timed from the switch's end, as
    its samples play (before: from before the switch, the drift of 2 s too early)."""
    import nanoasm.executor.motion_steps as steps
    from nanoasm.world.cantilever import SEED_LEVER

    planned = []

    def plan_dac(*args, **kwargs):
        planned.append(kwargs["t0"])
        return dac_plan(*args, **kwargs)

    dac_plan = steps.plan_dac
    monkeypatch.setattr(steps, "plan_dac", plan_dac)
    ctx, _ = _ctx()
    fake = SwitchingInstrument(ctx.config)
    push = _op(1, "a", (900.0, 1000.0), (1100.0, 1000.0))
    for k in range(2):
        drive(scan_line(ctx, np.array([45000.0, 45000.0]), np.array([45200.0, 45000.0]), 50), fake)
        assert ctx.timing.tapping
        fake.writes.clear()
        planned.clear()
        drive(stream_push(ctx, push, SEED_LEVER), fake)
        assert not ctx.timing.tapping and ctx.timing.approach == pytest.approx(2.0, abs=1e-6)
        touch = next(t for contact, t in fake.writes if contact)
        if k == 0:      # unknown yet: timed from before the switch, one write
            assert len(fake.writes) == 1 and planned[-1] < touch - 1.9
        else:           # a lifted travel first, then the push timed as it plays
            assert not fake.writes[0][0] and len(fake.writes) >= 2
            assert planned[-1] == pytest.approx(touch, abs=2.0 / ctx.config.sample_rate)
    state = ctx.timing.state_dict()
    assert LineTiming.from_state(state).approach == pytest.approx(2.0)
    assert LineTiming.from_state({"n": 0, "sums": [0, 0, 0, 0]}).approach == 0.0    # an older checkpoint


def test_a_scan_line_beyond_the_range_reads_bare_substrate_there():
    ctx, fake = _ctx("local-scan")
    hi = ctx.config.upper[0]
    profile = drive(scan_line(ctx, np.array([hi - 50.0, 45000.0]), np.array([hi + 50.0, 45000.0]), 101), fake)
    assert len(profile) == 101 and np.all(np.isfinite(profile))
    (a, b, n), = fake.lines
    assert b[0] <= hi and n < 101                                 # only the part within range is sent
    topic, doc = fake.emitted[-1]
    assert topic == "scan_line" and len(doc["heights"]) == 101


@given(st.floats(-200.0, 200.0), st.floats(-200.0, 200.0))
def test_a_pattern_counts_one_local_scan_and_its_time_apart_from_travel(dx, dy):
    ctx, fake = _ctx("local-scan")
    start = np.array([45000.0 + dx, 45000.0 + dy])

    def pattern():
        yield type("Line", (), {"a": start, "b": start + (100.0, 0.0), "n": 50})()
        yield type("Line", (), {"a": start + (0.0, 5.0), "b": start + (100.0, 5.0), "n": 50})()
        return "done"

    assert drive(run_pattern(ctx, pattern()), fake) == "done"
    assert ctx.ledger.counts["local_scans"] == 1
    assert ctx.ledger.times["local_scan"] + ctx.ledger.times["travel"] == pytest.approx(fake.t)
    assert ctx.scan_ref == 0.0                      # the first line's time: no travel before it
    assert fake.lines[1][0] == pytest.approx(tuple(start + (0.0, 5.0)))   # no drift: lines unshifted


def test_the_stuck_test_leaves_out_the_tips_own_friction_on_the_substrate():
    """At a normal force F_n the tip sliding on the substrate alone feels μ_ts F_n
    sideways: a lateral force just over the limit is the object's resistance only past
    that share (the instrument file's ``[friction] mu_ts``)."""
    from nanoasm.executor.monitor import PushMonitor
    from nanoasm.world.cantilever import SEED_LEVER as lever

    f_n = 50.0                                           # nN, pressed down
    s_n = np.full(40, f_n / (lever.spring_constant * lever.normal_gain))
    # over the limit by half μ F_n, the normal signal's cross-talk on the lateral added
    s_l = np.full(40, (300.0 + 0.5 * 0.1 * f_n) / lever.lateral_gain) + lever.crosstalk * s_n
    for friction, status in ((0.0, "stuck"), (0.1, "pushing")):
        mon = PushMonitor(f_n * 0.9, lever=lever, force_limit=300.0, friction=friction)
        mon.set_baseline(np.zeros(4), np.zeros(4))
        assert mon.check(s_n, s_l).status == status
    assert ExecOptions().substrate_friction == 0.0
    with pytest.raises(ValueError):
        ExecOptions(substrate_friction=-0.1)


def test_a_push_starts_from_the_last_after_scan_only_while_nothing_changed_since():
    """The before-scan is left out when the last push's after-scan located the same object,
    nothing was pushed since, no measurement revised the drift estimate and the scan is
    recent (issue 16); any of these failing scans first."""
    from nanoasm.executor.pushing import _fresh

    est, belief, refs = _kalman_setup()
    ctx = RunContext(InstrumentConfig(), ExecOptions(strategy="full", trust_after_scan=60.0), est, belief, refs,
                     moving={"p"})
    fake = FakeInstrument(ctx.config)
    fake.t = 20.0

    def fresh(obj="p"):
        return drive(_fresh(ctx, obj), fake)

    assert not fresh()                                               # no after-scan yet
    ctx.ledger.counts["pushes"] = 3
    ctx.last_after = ("p", 15.0, est.revision(), 3)
    assert fresh()
    assert not fresh("r1")                                           # another object's scan
    ctx.ledger.counts["pushes"] = 4                                  # something pushed since
    assert not fresh()
    ctx.ledger.counts["pushes"] = 3
    fake.t = 15.0 + ctx.options.trust_after_scan + 1.0               # too old
    assert not fresh()
    fake.t = 20.0
    est.measure("r1", (1001.0, 1000.0), np.eye(2), 18.0, refs, ["p"], set())   # a reference since
    assert not fresh()
    ctx.last_after = ("p", 19.0, est.revision(), 3)
    assert fresh()
    ctx.options = ExecOptions(strategy="full")                         # off by default
    assert not fresh()
    ctx.options = ExecOptions(strategy="local-scan", trust_after_scan=60.0)   # no filter to trust
    assert not fresh()


def test_the_drift_filter_counts_revisions_not_time():
    from nanoasm.drift import DriftFilter

    f = DriftFilter()
    r0 = f.revision
    f.predict_to(10.0)
    f.record_move(11.0, (3000.0, 0.0))
    f.inflate(offset_std=1.0)
    assert f.revision == r0
    f.measure(12.0, (1.0, 0.0))
    assert f.revision == r0 + 1
    f.reinitialise(13.0, (0.0, 0.0), np.eye(2))
    assert f.revision == r0 + 2


def test_a_push_that_lost_its_object_is_no_rejected_reference_but_one_not_found_after_is():
    from nanoasm.executor.drift_steps import suspect_drift

    ctx, fake = _ctx()
    for _ in range(3):                     # failed pushes: a reference is asked for, none counted
        drive(suspect_drift(ctx, "a", (1000.0, 1000.0), count=False), fake)
    assert ctx.drift.trust.rejected == [] and ctx.drift.needs_relocalisation(fake.t, ctx.options) is None
    drive(suspect_drift(ctx, "a", (1000.0, 1000.0)), fake)      # not where its after-scan looked
    assert ctx.drift.trust.rejected == ["a"]


def test_after_a_failed_push_references_are_taken_while_each_is_rejected(monkeypatch):
    import nanoasm.executor.drift_steps as steps

    ctx, fake = _ctx()
    taken = []

    def reference(ctx_, near, obj_id=None, *, force=False):       # each reference: the next verdict
        yield Msg("clock")
        ok = verdicts.pop(0)
        taken.append(ok)
        (ctx_.drift.trust.accept if ok else lambda t: ctx_.drift.reject(f"r{len(taken)}", t))(0.0)

    monkeypatch.setattr(steps, "take_reference", reference)
    monkeypatch.setattr(steps, "keep_track", lambda ctx_: (yield from ()) or False)
    for verdicts, want in (([True], [True]), ([False, True], [False, True]), ([False, False], [False, False])):
        taken.clear()
        ctx.drift.trust.accept()
        drive(steps.suspect_drift(ctx, "a", (1000.0, 1000.0), count=False), fake)
        assert taken == want                  # a shoved reference, then one that agrees; or a jump
    assert ctx.drift.trust.rejections == ctx.options.relocalise_rejections      # the jump's streak
