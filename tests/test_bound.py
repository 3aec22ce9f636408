"""The physical lower bound on a plan's instrument time (executor/bound.py)."""

from __future__ import annotations

import math

import pytest

from nanoasm.bodies import Body
from nanoasm.cad.layout import layout_from_dict
from nanoasm.dryrun import dry_run
from nanoasm.executor.bound import Bound, physical_bound
from nanoasm.executor.strategy import ExecOptions
from nanoasm.instrument import InstrumentConfig
from nanoasm.planner.plan import Expect, Operation, Plan
from nanoasm.world.params import TimingParams
from nanoasm.world.scene import scene_from_dict

TIP = 10.0


def push(op_id, obj, start, end, expect, angle=None):
    return Operation(op_id, obj, "t1", (start, end), Expect(expect, angle))


def test_one_straight_push_gives_its_closed_form():
    # a 1000 nm push of a 100 nm particle at 200 nm/s; four lines of 2 (R + r) = 120 nm at
    # 1 nm per 1 ms sample
    op = push(1, "p", (0.0, 0.0), (1000.0, 0.0), (1060.0, 0.0))
    objects = [Body("p", "particle", (-60.0, 0.0), 100.0)]
    b = physical_bound(Plan("x", operations=(op,)), ExecOptions(push_speed=200.0), InstrumentConfig(),
                       objects=objects)
    assert b.push_s == pytest.approx(1000.0 / 200.0)
    assert b.scan_s == pytest.approx(4 * 120.0 / 1000.0)
    assert b.travel_s == 0.0
    assert b.total_s == pytest.approx(5.48)
    assert b.switch_s == pytest.approx(2 * 2.0)        # into contact and back, 2 s each
    assert b.with_switches_s == pytest.approx(9.48)
    assert b.to_dict() == {"push_s": b.push_s, "scan_s": b.scan_s, "travel_s": 0.0, "switch_s": 4.0,
                           "total_s": b.total_s, "with_switches_s": b.with_switches_s}


def test_mode_switches_count_two_per_push_at_the_instruments_time():
    a = push(1, "p", (0.0, 0.0), (1000.0, 0.0), (1060.0, 0.0))
    b = push(2, "p", (1000.0, 0.0), (1500.0, 0.0), (1560.0, 0.0))
    plan = Plan("x", operations=(a, b))
    assert physical_bound(plan, timing=TimingParams(mode_switch=0.5)).switch_s == pytest.approx(2.0)
    assert physical_bound(plan, timing=TimingParams(mode_switch=0.0)).switch_s == 0.0


def test_without_objects_a_particle_radius_comes_from_the_contact_geometry():
    op = push(1, "p", (0.0, 0.0), (1000.0, 0.0), (1060.0, 0.0))   # R + r = 60
    b = physical_bound(Plan("x", operations=(op,)))
    assert b.scan_s == pytest.approx(0.48)
    rod = push(2, "r", (0.0, 0.0), (100.0, 0.0), (300.0, 50.0), angle=30.0)
    assert physical_bound(Plan("x", operations=(rod,))).scan_s == 0.0


def test_speeds_come_from_the_options_the_scanner_and_the_timing():
    op = push(1, "p", (0.0, 0.0), (1000.0, 0.0), (1060.0, 0.0))
    plan = Plan("x", operations=(op,))
    assert physical_bound(plan, ExecOptions(push_speed=500.0)).push_s == pytest.approx(2.0)
    # no push speed: the scanner's slew limit
    assert physical_bound(plan, ExecOptions(push_speed=None),
                          InstrumentConfig(max_speed=4000.0)).push_s == pytest.approx(0.25)
    assert physical_bound(plan, timing=TimingParams(scan_line_sample=0.002)).scan_s == pytest.approx(0.96)


def test_pushes_add_up_with_the_travel_between_them():
    a = push(1, "p", (0.0, 0.0), (1000.0, 0.0), (1060.0, 0.0))
    b = push(2, "q", (1000.0, 5000.0), (1000.0, 5300.0), (1000.0, 5360.0))   # bent path below
    one, two = (physical_bound(Plan("x", operations=(o,))) for o in (a, b))
    both = physical_bound(Plan("x", operations=(a, b)))
    assert both.push_s == pytest.approx(one.push_s + two.push_s)
    assert both.scan_s == pytest.approx(one.scan_s + two.scan_s)
    # 5000 nm apart, less the after-scan of one and the before-scan of the other (240 nm
    # each), at the 50 µm/s slew limit
    assert both.travel_s == pytest.approx((5000.0 - 480.0) / 50000.0)
    bent = Operation(3, "p", "t1", ((0.0, 0.0), (300.0, 0.0), (300.0, 400.0)), Expect((300.0, 460.0)))
    assert physical_bound(Plan("x", operations=(bent,))).push_s == pytest.approx(700.0 / 200.0)


def test_rods_count_three_lines_before_and_after():
    rod = Body("r", "rod", (0.0, 0.0), 80.0, 0.0, 800.0)
    op = push(1, "r", (-300.0, -70.0), (-300.0, 130.0), (0.0, 100.0), angle=10.0)
    b = physical_bound(Plan("x", operations=(op,)), objects={"r": rod})
    # each side: two cross lines of d + 2r = 100 and one axial line of L + 2r = 820, at 1 nm/ms
    assert b.scan_s == pytest.approx(2 * (2 * 100.0 + 820.0) / 1000.0)


def test_a_push_of_the_object_just_pushed_needs_no_lines_before_it():
    # the after-scan of the first push located it: the second counts its after-lines only,
    # and the travel between them loses no before-scan
    a = push(1, "p", (0.0, 0.0), (1000.0, 0.0), (1060.0, 0.0))
    b = push(2, "p", (1060.0, -60.0), (1060.0, 940.0), (1060.0, 1000.0))
    one = physical_bound(Plan("x", operations=(a,)))
    both = physical_bound(Plan("x", operations=(a, b)))
    assert both.scan_s == pytest.approx(one.scan_s * 1.5)              # 4 + 2 lines of 120 nm
    assert both.travel_s == 0.0                     # 85 nm apart, within the after-lines' 240 nm
    other = push(2, "q", (1060.0, -60.0), (1060.0, 940.0), (1060.0, 1000.0))
    assert physical_bound(Plan("x", operations=(a, other))).scan_s == pytest.approx(one.scan_s * 2)


def test_an_empty_plan_is_free():
    assert physical_bound(Plan("x")) == Bound(0.0, 0.0, 0.0)


def test_the_bound_stays_below_a_real_dry_run():
    scene = scene_from_dict({"format": "nanoasm.scene/1", "area": [2000, 2000], "seed": 3, "object": [
        {"id": "a", "kind": "particle", "at": [500, 600], "diameter": 100},
        {"id": "b", "kind": "particle", "at": [1500, 500], "diameter": 100},
        {"id": "c", "kind": "particle", "at": [600, 1500], "diameter": 100}]})
    layout = layout_from_dict({"format": "nanoasm.layout/1", "area": [2000, 2000], "target": [
        {"id": "t1", "kind": "particle", "at": [1000, 1000], "diameter": 100},
        {"id": "t2", "kind": "particle", "at": [1200, 1000], "diameter": 100}]})
    options = ExecOptions()
    out = dry_run(scene, layout, seed=3, options=options)
    b = physical_bound(out.summary.plan, options, scene.params.scanner, objects=out.summary.env,
                       timing=scene.params.timing)
    spent = out.report.instrument_time
    assert len(out.summary.plan.operations) == 2
    assert 0 < b.total_s <= spent.total - spent.full_scan
    assert b.with_switches_s <= spent.total - spent.full_scan
    assert b.switch_s <= spent.mode_switch
    assert b.scan_s <= spent.local_scan
    # the pushes were aimed again from where the scans found the objects: their lengths
    # differ from the plan's by the objects' scatter, a few nm
    assert b.push_s <= spent.push * 1.02
    assert math.isfinite(b.travel_s) and b.travel_s <= spent.travel
