"""A physical lower bound on the instrument time of a plan: what no executor can beat.

:func:`physical_bound` adds up, over a plan's pushes,

* **push**: the length of every ``tip_path`` at the push speed (``ExecOptions.push_speed``,
  at most the scanner's ``max_speed``);
* **scan**: the local scans of the seed's ch. 5 before and after each push with the
  fewest lines each pattern allows and each line no longer than it must be, at the scan
  speed;
* **travel**: the lifted moves between consecutive pushes, at the scanner's
  ``max_speed``.

Fewest lines (seed 5.2-5.3; the patterns of :mod:`~nanoasm.executor.local_scan` and
:mod:`~nanoasm.executor.rod_scan` when the first line finds the object): a particle
needs two lines before a push (L0 and V across it) and two after (L'0, V'); a rod needs
three before (two cross lines for its angle, as the executor measures it, and V along
its axis) and three after (two lines along the push that cross it, and V). A push of the
object the previous push moved needs none before it: that push's lines after it located
the object (the executor starts from them, ``ExecOptions.trust_after_scan``).

Shortest line: a line must cross the object's image from substrate to substrate to find
both edges, and a tip of apex radius ``r`` widens that image by ``r`` on each side: a
particle of radius R needs ``2 (R + r)``, a rod of diameter d ``d + 2 r`` across and
``L + 2 r`` along its axis. The drift and push-model margins (``r_max``) the executor
adds are not counted: a perfectly known position needs none.

Scan speed: sample spacing over sample time, the executor's
:class:`~nanoasm.executor.scan_lines.ScanOptions` spacing (``min(1, d / 20)`` nm by
default) over the instrument's ``TimingParams.scan_line_sample`` (1 ms by default), so
1 µm/s for objects of 20 nm and more.

Travel: from the end of one push's tip path to the start of the next, the tip covers at
least their distance D; the scan lines between them (after the one push, before the
next) may cover part of it, but never faster than travel, so the time is at least the
minimal scan time plus ``max(0, D - minimal scan length) / max_speed`` (a longer scan
costs more than the travel it saves, as the scan speed is below ``max_speed``).

Mode switches, apart (``switch_s``, not in ``total_s``): a push is made in contact mode
and its scans in tapping mode, so an executor that scans after every push, as the
closed loop must, switches into contact and back once per push, ``2 mode_switch`` each
(the instrument's ``TimingParams.mode_switch``, 2 s on the simulator). That is the
instrument's cost, not the physics': ``total_s`` leaves it out, ``with_switches_s``
adds it. On rods seed 1 the switches alone were twice the bound (bench/RESULTS.md).

Not included, so the bound stays a bound for any executor and any instrument: the full
scan and identification before the first push, the travel to the first push, the
settling time before each scan line (``scan_line_overhead``), lowering and lifting
the tip, acceleration limits (0.2 ms per push at the defaults), reference scans of
untouched objects for the drift filter, searches for lost objects, failed pushes,
corrections and replanned pushes. Distances are taken in the layout frame: drift moves
the scanner frame by a few nm over a push cycle (0.1 nm/s at the world's defaults),
which the bound ignores.

Objects: sizes come from ``objects`` (an :class:`~nanoasm.world.environment.Environment`
or bodies, e.g. the run's identified environment). Without them a particle's radius is
read from the plan's geometry (a push ends with the tip in contact: the distance from
the tip path's end to ``expect.at`` less the tip radius) and a rod, whose size the plan
does not give, counts no scan time.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass

from nanoasm.bodies import Body
from nanoasm.instrument import InstrumentConfig
from nanoasm.planner.plan import Operation, Plan
from nanoasm.world.params import TimingParams

from .scan_lines import DEFAULT_OPTIONS, ScanOptions
from .strategy import ExecOptions

#: Fewest lines of the ch. 5 patterns, before and after a push.
PARTICLE_LINES = (2, 2)
ROD_LINES = (3, 3)


@dataclass(frozen=True)
class Bound:
    """Instrument seconds no execution of the plan can beat, by activity."""

    push_s: float
    scan_s: float
    travel_s: float
    switch_s: float = 0.0

    @property
    def total_s(self) -> float:
        """Push, scan lines and travel: the bound for any instrument."""
        return self.push_s + self.scan_s + self.travel_s

    @property
    def with_switches_s(self) -> float:
        """:attr:`total_s` and the instrument's mode switches, two per push."""
        return self.total_s + self.switch_s

    def to_dict(self) -> dict:
        return {**asdict(self), "total_s": self.total_s, "with_switches_s": self.with_switches_s}


def path_length(points) -> float:
    """Length of a polyline (nm)."""
    return sum(math.dist(a, b) for a, b in zip(points[:-1], points[1:]))


def _bodies(objects) -> dict[str, Body]:
    if objects is None:
        return {}
    if isinstance(objects, Mapping):
        return dict(objects)
    seq = getattr(objects, "objects", objects)
    return {b.id: b for b in seq}


def _scan_lines(op: Operation, body: Body | None, tip_radius: float) -> tuple[float, float, float]:
    """(length of the minimal lines before + after the push, nm; their object's diameter
    for the sample spacing; number of lines)."""
    if body is not None and body.kind == "rod":
        d, L = body.diameter, body.length or body.diameter
        before = 2 * (d + 2 * tip_radius) + (L + 2 * tip_radius)
        return 2 * before, d, sum(ROD_LINES)
    if body is not None:
        R = body.diameter / 2
    elif op.expect.angle is None:
        R = max(math.dist(op.tip_path[-1], op.expect.at) - tip_radius, 0.0)
    else:
        return 0.0, 1.0, 0
    n = sum(PARTICLE_LINES)
    return n * 2 * (R + tip_radius), max(2 * R, 1e-9), n


def physical_bound(plan: Plan, options: ExecOptions | None = None, config: InstrumentConfig | None = None,
                   *, objects: Iterable[Body] | Mapping[str, Body] | None = None,
                   timing: TimingParams | None = None, scan: ScanOptions = DEFAULT_OPTIONS,
                   tip_radius: float = 10.0) -> Bound:
    """Lower bound on the instrument time of ``plan`` (see the module docstring for what
    is and is not counted).

    Parameters
    ----------
    plan : Plan
    options : ExecOptions, optional
        Its ``push_speed`` (default ``ExecOptions()``).
    config : InstrumentConfig, optional
        Its ``max_speed`` caps the push speed and sets the travel speed.
    objects : Environment, iterable of Body or mapping id -> Body, optional
        Sizes of the pushed objects (else inferred from the plan, see above).
    timing : TimingParams, optional
        Its ``scan_line_sample`` sets the scan speed and its ``mode_switch`` the switches'
        time (default ``TimingParams()``).
    scan : ScanOptions
        The executor's local-scan options (sample spacing).
    tip_radius : float
        Tip apex radius, nm.
    """
    options = options or ExecOptions()
    config = config or InstrumentConfig()
    timing = timing or TimingParams()
    bodies = _bodies(objects)
    v_push = config.max_speed if options.push_speed is None else min(options.push_speed, config.max_speed)
    push_s = scan_s = travel_s = 0.0
    prev_end = prev_object = None
    prev_scan = 0.0       # minimal scan length after the previous push, nm
    for op in plan.operations:
        push_s += path_length(op.tip_path) / v_push
        length, diameter, lines = _scan_lines(op, bodies.get(op.object), tip_radius)
        before = 0.0 if op.object == prev_object else length / 2
        if lines:
            scan_speed = scan.resolved(diameter).spacing / timing.scan_line_sample
            scan_s += (before + length / 2) / scan_speed
        if prev_end is not None:
            gap = math.dist(prev_end, op.tip_path[0]) - prev_scan - before
            travel_s += max(gap, 0.0) / config.max_speed
        prev_end, prev_scan, prev_object = op.tip_path[-1], length / 2, op.object
    return Bound(push_s, scan_s, travel_s, 2 * timing.mode_switch * len(plan.operations))
