"""Instrument time: the timing model and the per-activity ledger."""

from __future__ import annotations

import pytest

from nanoasm.executor.report import InstrumentTime
from nanoasm.world.params import TimingParams
from nanoasm.world.sim.clock import (
    ACTIVITIES,
    InstrumentClock,
    full_scan_time,
    push_time,
    scan_line_time,
    travel_time,
)

T = TimingParams()


def test_durations_at_the_defaults():
    assert full_scan_time(T, 512) == pytest.approx(512.0)  # 8.5 minutes per frame
    assert scan_line_time(T, 256) == pytest.approx(0.2 + 0.256)
    assert push_time(T, 1000.0) == pytest.approx(5.0)
    assert travel_time(T, 2000.0) == pytest.approx(1.0)


def test_each_charge_lands_in_its_activity():
    clock = InstrumentClock(T)
    clock.full_scan(256)
    clock.mode_switch("local_scan")
    clock.scan_line(100)
    clock.push(400.0)
    clock.travel(3000.0)
    clock.samples(500, 1000.0, "push")
    led = clock.ledger()
    assert led == pytest.approx({"full_scan": 256.0, "local_scan": 2.0 + 0.2 + 0.1,
                                 "push": 2.0 + 0.5, "travel": 1.5, "total": 256.0 + 2.3 + 2.5 + 1.5})
    assert clock() == clock.now == pytest.approx(led["total"])


def test_ledger_is_the_reports_instrument_time():
    clock = InstrumentClock(T)
    clock.push(100.0)
    rec = InstrumentTime(**clock.ledger())
    assert rec.push == pytest.approx(0.5) and rec.total == pytest.approx(0.5)
    assert set(clock.ledger()) == {*ACTIVITIES, "total"}


def test_many_small_charges_add_up_exactly():
    one, many = InstrumentClock(T), InstrumentClock(T)
    one.samples(100_000, 1000.0, "travel")
    for _ in range(100_000):
        many.samples(1, 1000.0, "travel")
    assert one.now == many.now == 100.0


def test_start_time_is_not_charged():
    clock = InstrumentClock(T, start=10.0)
    clock.travel(200.0)
    assert clock.now == pytest.approx(10.1) and clock.ledger()["total"] == pytest.approx(0.1)


def test_bad_charges_are_refused():
    clock = InstrumentClock(T)
    with pytest.raises(ValueError, match="unknown activity 'idle'"):
        clock.advance(1.0, "idle")
    with pytest.raises(ValueError, match="not negative"):
        clock.advance(-1.0, "push")
    with pytest.raises(ValueError, match="distance"):
        clock.push(float("nan"))
    assert clock.now == 0.0
