"""Execution strategies and the knobs of a run.

=============  ============  ============  ==============  ===========  =================
strategy       local scans   drift filter  re-aim pushes   replanning   reference
=============  ============  ============  ==============  ===========  =================
open-loop      no            no            no              no           none
local-scan     yes (ch. 5)   no            yes             no           none
kalman         yes           yes           yes             no           untouched objects
full           yes           yes           yes             yes          untouched objects
anchor         yes           no            yes             no           one fixed feature
=============  ============  ============  ==============  ===========  =================
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass


class Strategy(str, enum.Enum):
    OPEN_LOOP = "open-loop"
    LOCAL_SCAN = "local-scan"
    KALMAN = "kalman"
    FULL = "full"
    ANCHOR = "anchor"

    @property
    def scans(self) -> bool:
        return self is not Strategy.OPEN_LOOP

    @property
    def kalman(self) -> bool:
        return self in (Strategy.KALMAN, Strategy.FULL)

    @property
    def replans(self) -> bool:
        return self is Strategy.FULL

    @property
    def anchored(self) -> bool:
        return self is Strategy.ANCHOR


STRATEGIES = tuple(s.value for s in Strategy)


@dataclass(frozen=True)
class ExecOptions:
    """Knobs of a run (nm, s). Each appears in the speed-versus-error benchmark.

    Parameters
    ----------
    strategy : Strategy
    pixel_size : float
        Pixel of the first full scan, nm (identification needs about 20 nm or finer).
    r_max : float
        Largest expected position error when no drift filter bounds it, nm.
    max_drift_rate : float
        Without a drift filter: the fastest drift assumed, nm/s; r_max grows by it with
        the time since an object was last seen.
    r_max_floor : float
        Least r_max used even with a confident filter (object scatter, scan noise), nm.
    line_factor : float
        Multiplies the r_max that sets local-scan line lengths (shorter lines are faster
        but miss more often).
    scan_spacing : float or None
        Distance between the samples of a local-scan line, nm (None: ``min(1, R / 10)``
        for an object of radius ``R``); the count of samples per line, so its time.
    reference_every : float
        A drift reference is measured before a push when the last one is older than
        this, s (kalman, full, anchor).
    drift_q : float
        Process noise of the drift filter: random walk of the drift velocity, nm²/s³.
    drift_q_offset : float
        White noise on the drift offset, nm²/s: the world's random walk squared (0.01 for
        the examples' 0.1 nm/√s) plus what the creep model misses. At 1, a drift reference
        shoved 51 nm by a rod passed the gate in the bowtie dry-run (seed 7); the effect
        of 0.01 and 1 on every scene family is in ``bench/RESULTS.md``.
    max_corrections : int
        Extra pushes allowed to bring an object that missed its slot back in.
    max_failures : int
        Pushes of one object that fail or leave it off course (``replan_after``) after
        which it is left where it is: it becomes an obstacle to the planner and its slot
        goes to another object.
    replan_after : float
        With replanning (``full``): an object this far off its planned course after a
        push (nm), or a failed push, has the rest planned again; smaller deviations are
        absorbed by re-aiming the next push.
    lost_radius : float
        Half-size of the widening search for an object that is not where expected, nm.
    push_speed : float or None
        Tip speed while pushing, nm/s (None: the scanner's limit).
    chunk : int
        DAC samples per streamed chunk.
    force_limit : float
        Lateral force, nN, beyond which a push is stopped as stuck.
    """

    strategy: Strategy = Strategy.FULL
    pixel_size: float = 10.0
    r_max: float = 150.0
    max_drift_rate: float = 0.5
    r_max_floor: float = 15.0
    line_factor: float = 1.0
    scan_spacing: float | None = None
    reference_every: float = 120.0
    drift_q: float = 1e-6
    drift_q_offset: float = 0.1
    max_corrections: int = 2
    max_failures: int = 3
    replan_after: float = 60.0
    lost_radius: float = 1500.0
    push_speed: float | None = 200.0
    chunk: int = 4096
    force_limit: float = 300.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "strategy", Strategy(self.strategy))
        for name in ("pixel_size", "r_max", "max_drift_rate", "r_max_floor", "line_factor", "reference_every",
                     "lost_radius", "force_limit", "replan_after", "scan_spacing", "push_speed"):
            v = getattr(self, name)
            if v is None and name in ("scan_spacing", "push_speed"):      # None: the default rule
                continue
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be positive and finite, got {v!r}")
        for name in ("drift_q", "drift_q_offset"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v!r}")
        if self.max_corrections < 0 or self.chunk < 16 or self.max_failures < 1:
            raise ValueError("max_corrections must be >= 0, max_failures >= 1 and chunk >= 16")
