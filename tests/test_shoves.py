"""A push whose object ends over a believed neighbour shoved it: the neighbour is located
again at once, and one the plan holds in a slot is pushed back in (executor/shoves.py,
after_push.shoved_back). ``rods`` seed 5 (fdf97c3): a particle pushed beside a placed
rod's end shoved it 22 nm; nothing looked at the rod again, and the report called its slot
filled where the rod lay 20.9 nm off."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

import pytest
from simkit import particle, rod, world

from nanoasm.bodies import Body
from nanoasm.cad.layout import Layout, Tolerance
from nanoasm.executor.after_push import shoved_back
from nanoasm.executor.belief import Belief
from nanoasm.executor.context import RunContext
from nanoasm.executor.course import Course
from nanoasm.executor.documents import EVENT
from nanoasm.executor.engine import RunEngine
from nanoasm.executor.estimators import NoDrift
from nanoasm.executor.references import References
from nanoasm.executor.shoves import OVERLAP, after_push, look_at_shoved, overlapping
from nanoasm.executor.strategy import ExecOptions
from nanoasm.planner import PlanOptions
from nanoasm.planner.plan import Assignment, Expect, Operation, Plan
from nanoasm.world.environment import EnvObject, Environment

ROD = dict(diameter=70.0, angle=0.0, length=600.0)


def _ctx(objects, config=None):
    env = Environment((4000.0, 4000.0), tuple(objects), ())
    return RunContext(config, ExecOptions(strategy="local-scan", r_max=60.0), NoDrift((0.0, 0.0), 0.0),
                      Belief(env, 0.0), References())


def _believed(p_at, rod_at=(2000.0, 2000.0)):
    """The pushed particle p (90 nm) where its scan after found it, and rod r where it was believed."""
    return [EnvObject("p", "particle", p_at, 90.0),
            EnvObject("r", "rod", rod_at, ROD["diameter"], ROD["angle"], ROD["length"])]


def test_only_an_overlap_beyond_two_scans_errors_counts():
    # r's core runs from x = 1735 to 2265; p and r footprints meet where p's centre is 80 nm from it
    for x, overlaps in ((1655.0 + OVERLAP - 1.0, False), (1655.0 + OVERLAP + 1.0, True), (1640.0, False),
                        (1700.0, True)):
        got = overlapping(_ctx(_believed((x, 2000.0))), "p")
        assert [oid for oid, _ in got] == (["r"] if overlaps else []), x
    (oid, shift), = overlapping(_ctx(_believed((1670.0, 2000.0))), "p")
    assert np.allclose(shift, (15.0, 0.0))                # out of the overlap, away from p
    assert overlapping(_ctx(_believed((1670.0, 2000.0))), "p", exclude={"r"}) == []
    ctx = _ctx(_believed((1670.0, 2000.0)))
    ctx.belief.touched.add("r")                          # pushed, not seen since: no belief to compare
    assert overlapping(ctx, "p") == []


def _look(truth, believed):
    sim = world(truth)
    ctx = _ctx(believed, sim.config)
    events: list[str] = []
    engine = RunEngine(sim, [lambda topic, doc: events.append(doc.text) if topic == EVENT else None])
    return engine.run(look_at_shoved(ctx, "p")), ctx, events


def test_a_shoved_rod_is_located_where_the_shove_left_it():
    # the push left p at 1670 and shoved the rod 25 nm along its axis, to 2025
    truth = [particle((1670, 2000), d=90.0, id="p"), rod((2025, 2000), 0.0, 600.0, d=70.0, id="r")]
    found, ctx, events = _look(truth, _believed((1670.0, 2000.0)))
    assert found == ["r"] and ctx.shoved == {"r"}
    assert math.dist(ctx.belief["r"].at, (2025.0, 2000.0)) < 5.0
    assert any("r: shoved by the push of p" in e for e in events)


@pytest.mark.parametrize("beyond", [False, True])
def test_no_shove_is_looked_for_after_a_push_that_left_its_object_off_course(beyond):
    """p found overlapping the rod after its push: the rod is looked for when p lies within
    ``replan_after`` of where its push was to leave it, not when it lies beyond (such a
    push went astray or met a drift jump, and says nothing of a shove)."""
    truth = [particle((1670, 2000), d=90.0, id="p"), rod((2025, 2000), 0.0, 600.0, d=70.0, id="r")]
    believed = _believed((1670.0, 2000.0))
    sim = world(truth)
    ctx = _ctx(believed, sim.config)
    off = ctx.options.replan_after + (10.0 if beyond else -10.0)
    op = Operation(1, "p", "s1", ((1500.0, 2000.0), (1670.0 - off, 2000.0)), Expect((1670.0 - off, 2000.0)))
    RunEngine(sim, []).run(after_push(ctx, op, believed[0]))
    assert ctx.shoved == (set() if beyond else {"r"})
    assert (ctx.ledger.counts["local_scans"] == 0) == beyond


def test_a_neighbour_clear_of_the_push_is_not_scanned():
    truth = [particle((1640, 2000), d=90.0, id="p"), rod((2000, 2000), 0.0, 600.0, d=70.0, id="r")]
    found, ctx, events = _look(truth, _believed((1640.0, 2000.0)))
    assert found == [] and not ctx.shoved and ctx.ledger.counts["local_scans"] == 0


def _asm(belief_at, ops=()):
    slot = Body("s1", "particle", (1000.0, 1000.0), 90.0)
    layout = Layout((4000.0, 4000.0), (slot,), tolerance=Tolerance(position=20.0))
    ctx = _ctx([EnvObject("a", "particle", belief_at, 90.0)])
    ctx.shoved.add("a")
    plan = Plan(None, (Assignment("s1", "a"),), tuple(ops))
    asm = SimpleNamespace(ctx=ctx, layout=layout, options=ctx.options, plan_options=PlanOptions(),
                          course=Course(), replanner=SimpleNamespace(plan=plan), first_plan=plan)
    return asm, list(ops)


def test_a_shoved_object_in_its_slot_is_pushed_back_in():
    asm, ops = _asm((1016.0, 1000.0))                    # shoved 16 nm: within 20, beyond the tight 12
    corrections: dict[str, int] = {}
    shoved_back(asm, ops, 0, corrections)
    assert ops and all(p.object == "a" and p.target == "s1" for p in ops)
    assert math.dist(ops[-1].expect.at, (1000.0, 1000.0)) < 5.0
    assert corrections == {"a": 1} and not asm.ctx.shoved


def test_a_shoved_object_still_within_the_tight_tolerance_is_left():
    asm, ops = _asm((1008.0, 1000.0))
    shoved_back(asm, ops, 0, {})
    assert ops == [] and not asm.ctx.shoved

