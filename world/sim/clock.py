"""Instrument time: the timing model of each activity and a clock with a per-activity ledger.

The simulated instrument charges its clock for what it does; the ledger is the report's
``instrument_time`` (``full_scan``, ``local_scan``, ``push``, ``travel``, ``total``).
Time is kept in integer nanoseconds, so many small charges add up exactly. Mode
switches (approach, retract, tapping on or off) are charged to the activity that needed
them. Durations at the seed-like defaults: a 512-line full scan takes 8.5 minutes, a
1 µm push 5 s, a 256-sample local scan line 0.46 s.
"""

from __future__ import annotations

import math

from nanoasm.world.params import TimingParams

#: Activities of the ledger, in report order (``total`` is their sum).
ACTIVITIES = ("full_scan", "local_scan", "push", "travel")


def _nonnegative(name: str, value: float) -> float:
    if not (math.isfinite(value) and value >= 0):
        raise ValueError(f"{name} must be finite and not negative, got {value}")
    return float(value)


def full_scan_time(timing: TimingParams, lines: int) -> float:
    """Seconds for a full scan of ``lines`` lines (trace and retrace each)."""
    return _nonnegative("lines", lines) * timing.full_scan_line


def scan_line_time(timing: TimingParams, samples: int) -> float:
    """Seconds for one local scan line of ``samples`` samples, settling included."""
    return timing.scan_line_overhead + _nonnegative("samples", samples) * timing.scan_line_sample


def push_time(timing: TimingParams, distance: float) -> float:
    """Seconds to push over ``distance`` nm at the push speed."""
    return _nonnegative("distance", distance) / timing.push_speed


def travel_time(timing: TimingParams, distance: float) -> float:
    """Seconds to travel ``distance`` nm with the tip lifted."""
    return _nonnegative("distance", distance) / timing.travel_speed


class InstrumentClock:
    """The instrument's clock and ledger; ``clock()`` gives the time in seconds."""

    def __init__(self, timing: TimingParams, start: float = 0.0):
        self.timing = timing
        self._start_ns = round(_nonnegative("start", start) * 1e9)
        self._ns = dict.fromkeys(ACTIVITIES, 0)

    def __call__(self) -> float:
        return self.now

    @property
    def now(self) -> float:
        """Instrument time in seconds."""
        return (self._start_ns + sum(self._ns.values())) / 1e9

    def advance(self, seconds: float, activity: str) -> float:
        """Charge ``seconds`` to ``activity``; returns the new time."""
        if activity not in self._ns:
            raise ValueError(f"unknown activity {activity!r} (one of {', '.join(ACTIVITIES)})")
        self._ns[activity] += round(_nonnegative("seconds", seconds) * 1e9)
        return self.now

    def samples(self, n: int, sample_rate: float, activity: str) -> float:
        """Charge ``n`` DAC samples streamed at ``sample_rate`` Hz."""
        return self.advance(_nonnegative("n", n) / sample_rate, activity)

    def full_scan(self, lines: int) -> float:
        return self.advance(full_scan_time(self.timing, lines), "full_scan")

    def scan_line(self, samples: int) -> float:
        return self.advance(scan_line_time(self.timing, samples), "local_scan")

    def push(self, distance: float) -> float:
        return self.advance(push_time(self.timing, distance), "push")

    def travel(self, distance: float) -> float:
        return self.advance(travel_time(self.timing, distance), "travel")

    def mode_switch(self, activity: str) -> float:
        """Charge one approach/retract (a switch between scanning and pushing)."""
        return self.advance(self.timing.mode_switch, activity)

    def ledger(self) -> dict[str, float]:
        """Seconds per activity and their ``total``, as the report's ``instrument_time``."""
        out = {a: ns / 1e9 for a, ns in self._ns.items()}
        out["total"] = sum(self._ns.values()) / 1e9
        return out
