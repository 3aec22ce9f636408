"""Execution strategies and the knobs of a run.

=============  ============  ============  ==============  ===========  ======================
strategy       local scans   drift filter  re-aim pushes   replanning   reference
=============  ============  ============  ==============  ===========  ======================
open-loop      no            no            no              no           none
local-scan     yes (ch. 5)   no            yes             no           none
kalman         yes           yes           yes             no           untouched objects,
                                                                        fixed features
full           yes           yes           yes             yes          as kalman
anchor         yes           no            yes             no           one untouched particle
=============  ============  ============  ==============  ===========  ======================
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, replace

from nanoasm.param import param, validate
from nanoasm.world.limits import MIN_PUSH_SPEED


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
    reference_sigma : float
        ...or when the drift estimate's σ (worst direction) is above this, nm (kalman, full).
    relocalise_sigma : float
        The drift estimate is relocalised (a window of the full scan scanned again and
        registered) when its σ passes this, nm (kalman, full).
    relocalise_rejections : int
        ...or when this many drift references in a row are not where it puts them.
    relocalise_pause : float
        ...or when a resumed run stood still this long, s.
    relocalise_window : float
        Side of the window scanned to relocalise, nm.
    creep_amplitude_std : float
        Standard deviation of the creep amplitude the drift filter assumes, per decade
        (the nominal amplitude is 0.01; a real scanner's is known to about ±30 %).
    creep_tau_std : float
        Standard deviation of the logarithm of the creep time constant the drift filter
        assumes (±30 % is about 0.2): each long move widens the estimate along its step.
    push_heading_std : float
        Scatter of a pushed particle's direction of motion about the tip's, degrees: with
        ``capture_angle`` it sets the legs of a long push (:mod:`.push_legs`).
    capture_angle : float
        Half-angle of the cone about the tip's motion within which the tip carries a
        particle, degrees.
    between_legs : {"line", "contact", "contact-only"}
        How a long push's particle is located between its legs: a line across, or
        (``"contact"``, the default) the leg's contact angle (:mod:`.contact_angle`), a
        line only before the last leg and where the angle is too uncertain
        (``"contact-only"``: not before the last leg either; on the particle families 5-23 %
        less instrument time after the full scan, the same fill, median RMS 0.1-0.4 nm
        higher, ``bench/RESULTS.md``). ``"contact"``
        takes 20-36 % less instrument time per filled slot on the families of long pushes
        (allpushed 41.3 -> 32.9 s, wide 70.5 -> 45.0 s) and fills as many slots
        (``bench/RESULTS_pushes.md``). Its legs are tracked: the angle is read as the tip
        pushes and a leg stopped once the particle slides far round the tip, so the
        legs before the last may run longer (:mod:`.push_legs`).
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
    repair_rounds : int
        With replanning (``full``): rounds of survey and pushes after the check scans
        while particle slots are not filled, or filled only near the edge of their
        tolerance (:mod:`.edge_slots`), and the run pushed something (:mod:`.repair`);
        0: none.
    replan_after : float
        With replanning (``full``): an object this far off its planned course after a
        push (nm), or a failed push, has the rest planned again; smaller deviations are
        absorbed by re-aiming the next push.
    lost_radius : float
        Half-size of the widening search for an object that is not where expected, nm.
    trust_after_scan : float
        A push starts from where its object's last after-scan put it, without a scan
        before, when that scan is at most this old (s), nothing was pushed since and no
        measurement revised the drift estimate since (issue 16: the before-scan of a
        rod's next push repeated the after-scan of its last). 0, the default: every push
        scans first. At 60 s the rods family took 14 % less instrument time after the full
        scan at equal fill, but a drift jump between two pushes of one object then costs a
        push made from the stale position (``bench/RESULTS.md``).
    contact_batch : int
        Pushes of different particles made in one contact phase, each located before
        and scanned after all of them (:mod:`.batching`): two mode switches for the group
        instead of two a push. 4 by default; 1: each push scanned after before the next.
    push_speed : float or None
        Tip speed while pushing, nm/s (None: the scanner's limit).
    chunk : int
        DAC samples per streamed chunk.
    force_limit : float
        Lateral force, nN, beyond which a push is stopped as stuck.
    substrate_friction : float
        ``μ_ts``, the tip's friction coefficient on the substrate (the instrument file's
        ``[friction] mu_ts``, a dry-run's calibration): the lateral force ``μ_ts F_n`` the
        tip feels sliding on the substrate is not the object's resistance, so the stuck
        test leaves it out. 0: all of it counts.
    slip_sigmas : float
        The preload of a push presses the tip at least with the least normal force that
        keeps it down (seed eq. 4.7, 4.20) this many standard deviations of its
        object-to-object spread above the nominal one (:mod:`.contact_load`); never below
        the instrument's preload. Negative: the instrument's preload alone.
    """

    strategy: Strategy = param(Strategy.FULL, "", "execution strategy")
    pixel_size: float = param(10.0, "nm", "pixel of the first full scan", positive=True)
    r_max: float = param(150.0, "nm", "largest expected position error without a drift filter",
                         positive=True)
    max_drift_rate: float = param(0.5, "nm/s", "fastest drift assumed without a drift filter",
                                  positive=True)
    r_max_floor: float = param(15.0, "nm", "least r_max used", positive=True)
    line_factor: float = param(1.0, "-", "multiplies the r_max that sets local-scan line lengths",
                               positive=True)
    scan_spacing: float | None = param(None, "nm", "distance between the samples of a local-scan line "
                                       "(None: min(1, R / 10))", optional=True, positive=True)
    reference_every: float = param(120.0, "s", "largest age of the last drift reference before a push",
                                   positive=True)
    reference_sigma: float = param(6.0, "nm", "drift σ above which a reference is measured before a push",
                                   positive=True)
    relocalise_sigma: float = param(40.0, "nm", "drift σ above which the estimate is relocalised",
                                    positive=True)
    relocalise_rejections: int = param(2, "-", "references rejected in a row that relocalise", lo=1)
    relocalise_pause: float = param(300.0, "s", "stand-still of a resumed run that relocalises",
                                    positive=True)
    relocalise_window: float = param(2000.0, "nm", "side of the window scanned to relocalise",
                                     positive=True)
    creep_amplitude_std: float = param(0.002, "1/decade", "standard deviation of the creep amplitude "
                                       "the drift filter assumes", nonnegative=True)
    creep_tau_std: float = param(0.2, "-", "standard deviation of the creep time constant's logarithm "
                                 "the drift filter assumes", nonnegative=True, hi=2.0)
    push_heading_std: float = param(2.0, "deg", "scatter of a pushed particle's direction about the tip's",
                                    positive=True, hi=45.0)
    capture_angle: float = param(45.0, "deg", "half-angle of the cone within which the tip carries a particle",
                                 positive=True, hi=90.0)
    between_legs: str = param("contact", "-", "how a particle is located between a push's legs",
                              choices=("line", "contact", "contact-only"))
    drift_q: float = param(1e-6, "nm²/s³", "random walk of the drift velocity", nonnegative=True)
    drift_q_offset: float = param(0.1, "nm²/s", "white noise on the drift offset", nonnegative=True)
    max_corrections: int = param(2, "-", "extra pushes to bring an object into its slot", nonnegative=True)
    max_failures: int = param(3, "-", "failed or off-course pushes of one object before it is left",
                              lo=1)
    repair_rounds: int = param(1, "-", "survey-and-push rounds after the check scans while particle "
                               "slots are not filled or only near the edge", nonnegative=True)
    replan_after: float = param(60.0, "nm", "deviation from the planned course that replans (full)",
                                positive=True)
    lost_radius: float = param(1500.0, "nm", "half-size of the search for a lost object", positive=True)
    after_scan: str = param("predicted", "-", "the scan after a push: short lines where the push model puts the "
                            "object first, the seed's pattern if it is not there (predicted), so for rods only "
                            "(rods), or the seed's pattern only (seed)", choices=("predicted", "rods", "seed"))
    trust_after_scan: float = param(0.0, "s", "age of an after-scan a push may start from without a scan "
                                    "before (0: always scan first)", nonnegative=True)
    contact_batch: int = param(4, "-", "pushes of different particles made in one contact phase, scanned "
                               "after all of them (1: each scanned after before the next)", lo=1, hi=64)
    push_speed: float | None = param(200.0, "nm/s", "tip speed while pushing (None: the scanner's limit)",
                                     optional=True, positive=True, lo=MIN_PUSH_SPEED)
    chunk: int = param(4096, "-", "DAC samples per streamed chunk", lo=16)
    force_limit: float = param(300.0, "nN", "lateral force beyond which a push is stopped as stuck",
                               positive=True)
    substrate_friction: float = param(0.0, "-", "tip-substrate friction coefficient mu_ts (the stuck test "
                                      "leaves the tip's own friction out)", nonnegative=True, hi=2.0)
    slip_sigmas: float = param(2.5, "-", "spread of the least normal force (eq. 4.7) a push's preload "
                               "covers, standard deviations; negative: the instrument's preload", lo=-1.0, hi=6.0)

    def __post_init__(self) -> None:
        validate(self)

    def batched(self, contact_batch: int | None) -> ExecOptions:
        """These options with ``contact_batch`` (None: as they are): ``--contact-batch``, or
        a resumed run's checkpoint (:func:`.checkpoints.checkpoint_batch`)."""
        return self if contact_batch is None else replace(self, contact_batch=contact_batch)
