"""Contact monitoring during a push, from the photodiode signals (seed 3.5, Fig. 3.20).

Signals are compensated as eq. 3.28 with the calibration's baseline maps A(i, j), B(i, j)
at each sample's scanner position (eq. 3.29, :class:`~.baselines.BaselineMaps`) and the
normal-to-lateral cross-talk α: ``S̄n = S_n − A(i, j)``, ``S̄l = S_l − B(i, j) − α S̄n``.
Without maps, the baselines are scalars measured in free air just before the push
(``S_n0``, ``S_l0``), at the travel height: the substrate's reflection there is not the
one in contact (seed Fig. 3.13), which biases S̄n.
Forces follow eq. 3.11: ``F_n = k K_n S̄n`` and the lateral force ``(k_l K_l / h) S̄l``.

* contact: S̄n reaches half the preload's deflection;
* slip-over: after contact, S̄n collapses below ``slip_fraction`` of the contact level
  for a few samples (the tip went over the object, Fig. 3.20);
* stuck: the lateral force, less the tip's own sliding friction on the substrate
  ``μ_ts F_n`` (the instrument file's ``[friction] mu_ts``, seed §3.4.3), stays beyond
  ``force_limit`` (the object does not move).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nanoasm.world.cantilever import SEED_LEVER, Cantilever

from .baselines import BaselineMaps

#: Consecutive samples a condition must hold to count (rejects single-sample noise).
HOLD = 3


@dataclass(frozen=True)
class Verdict:
    """``status``: "pushing" (all well so far), "slipped", "stuck" or "no_contact";
    ``index``: first sample of the failure within the block; ``peak_force`` nN;
    ``contact``: where the object sat on the tip at the push's end
    (:class:`~.contact_angle.ContactAngle`), when measured; ``stopped``: where the tip
    was (layout frame nm) when a tracked push was stopped short on its contact angle;
    ``felt``: False when it was stopped blind with nothing pressing on the tip (the object
    left behind, or carried by a force within the friction's scatter: a line across tells)."""

    status: str
    index: int | None = None
    peak_force: float = 0.0
    contact: object | None = None
    stopped: tuple[float, float] | None = None
    felt: bool = True

    @property
    def failed(self) -> bool:
        return self.status in ("slipped", "stuck", "no_contact")


def _run_start(mask: np.ndarray, hold: int = HOLD) -> int | None:
    """First index where ``mask`` holds for ``hold`` consecutive samples."""
    if mask.size < hold:
        return None
    run = np.convolve(mask.astype(int), np.ones(hold, int), mode="valid")
    hits = np.flatnonzero(run == hold)
    return int(hits[0]) if hits.size else None


class PushMonitor:
    """Watches the signals of one push, block by block."""

    def __init__(self, preload: float, *, lever: Cantilever = SEED_LEVER, force_limit: float = 300.0,
                 slip_fraction: float = 0.4, baselines: BaselineMaps | None = None, friction: float = 0.0):
        self.lever = lever
        self.friction = friction                          # μ_ts: the tip's own lateral force per F_n
        self.baselines = baselines
        self.level = preload / lever.normal_gain          # S̄n in contact at the preload, V
        self.force_limit = force_limit
        self.slip_fraction = slip_fraction
        self.s_n0 = 0.0
        self.s_l0 = 0.0
        self.in_contact = False
        self.peak = 0.0
        self.contact_samples = 0

    def set_baseline(self, s_n: np.ndarray, s_l: np.ndarray) -> None:
        """Free-air baseline from samples with the tip lifted (eq. 3.28's A and B here),
        unless the maps give them."""
        if len(s_n) and self.baselines is None:
            self.s_n0 = float(np.median(s_n))
            self.s_l0 = float(np.median(s_l))

    @property
    def baseline_key(self) -> tuple[float, float]:
        """What :meth:`compensated` depends on beyond its samples and the fixed maps and
        lever: the free-air baselines (a key under which its values may be kept)."""
        return self.s_n0, self.s_l0

    def compensated(self, s_n: np.ndarray, s_l: np.ndarray, xy=None) -> tuple[np.ndarray, np.ndarray]:
        """``(S̄n, S̄l)`` (eq. 3.28) of samples taken at scanner positions ``xy`` ``(n, 2)`` nm."""
        if self.baselines is not None and xy is not None:
            return self.baselines.compensate(s_n, s_l, xy, self.lever.crosstalk)
        sn = np.asarray(s_n, float) - self.s_n0
        sl = np.asarray(s_l, float) - self.s_l0 - self.lever.crosstalk * sn
        return sn, sl

    def forces(self, s_n, s_l, xy=None) -> tuple[np.ndarray, np.ndarray]:
        """Normal and lateral force, nN (eq. 3.33-3.34 with the compensated signals)."""
        sn, sl = self.compensated(s_n, s_l, xy)
        return self.lever.spring_constant * self.lever.normal_gain * sn, self.lever.lateral_gain * sl

    def check(self, s_n: np.ndarray, s_l: np.ndarray, xy=None) -> Verdict:
        """Verdict on the push samples of one block (in order), taken at scanner ``xy``."""
        sn, sl = self.compensated(s_n, s_l, xy)
        f_l = self.lever.lateral_gain * sl
        f_n = self.lever.spring_constant * self.lever.normal_gain * sn
        if f_l.size:
            self.peak = max(self.peak, float(np.max(np.abs(f_l))))
        start = 0
        if not self.in_contact:
            touch = _run_start(sn >= 0.5 * self.level)
            if touch is None:
                self.contact_samples = 0
                return Verdict("pushing", None, self.peak)
            self.in_contact = True
            start = touch
        self.contact_samples += sn.size - start
        slip = _run_start(sn[start:] < self.slip_fraction * self.level)
        resist = np.abs(f_l[start:]) - self.friction * np.maximum(f_n[start:], 0.0)   # the object's share
        stuck = _run_start(resist > self.force_limit)
        firsts = [(i, s) for i, s in ((slip, "slipped"), (stuck, "stuck")) if i is not None]
        if firsts:
            i, status = min(firsts)
            return Verdict(status, start + i, self.peak)
        return Verdict("pushing", None, self.peak)

    def finish(self) -> Verdict:
        """After the last block: a push that never touched down is a failure too."""
        return Verdict("pushing" if self.in_contact else "no_contact", None, self.peak)
