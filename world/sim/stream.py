"""Playing one chunk of DAC samples: vectorised far from objects, sample by sample near them.

The chunk's samples are split into runs. A sample is *slow* when the tip is in contact
(z ≤ 0) and within the contact distance plus a margin of an object; every other sample is
*fast*: lifted, or in contact far from every object. Fast runs cost a few array
operations whatever their length and however many objects the sample holds (a lifted
sample higher than the tallest object skips even the spatial query); slow runs step the
pushing physics (:class:`~nanoasm.world.sim.push.PushPhysics`) once per sample. Pushes in
progress end at the first fast sample. Once a slow run has moved something, the rest of
the chunk is classified again.

The tip, in the sample frame, is at ``piezo + deflection offset - drift offset``. Its
deflection is ``max(0, H - z)`` with H the apex height of the surface under it (0 on the
substrate, plateaus over obstacles, an object's profile when a lifted tip grazes it or
the tip rides over one).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from nanoasm.drift.creep import creep_moves

from .drift_model import DriftModel
from .push import PushPhysics
from .signals import SignalModel, twist_deg


@dataclass
class TipState:
    """The tip at the last sample played: piezo XY (scanner), tip XY (sample frame), Z, S̄_l,
    ride, the direction of the lateral motion and the lateral force on the tip (nN, AFM frame)."""

    piezo: np.ndarray
    tip: tuple[float, float]
    z: float
    sl_bar: float = 0.0
    ride: float = 0.0
    motion: np.ndarray = field(default_factory=lambda: np.zeros(2))
    force: np.ndarray = field(default_factory=lambda: np.zeros(2))


@dataclass(frozen=True, eq=False)
class Played:
    """Per sample: deflection (nm), lateral force on the tip ``(n, 2)`` (nN, AFM frame), tip
    ``(n, 2)``."""

    deflection: np.ndarray
    force: np.ndarray
    tip: np.ndarray


def play_chunk(world: PushPhysics, model: SignalModel, nm: np.ndarray, off: np.ndarray,
               state: TipState, max_step: float) -> Played:
    """Play scanner-frame samples ``nm`` ``(n, 3)`` with drift offsets ``off`` ``(n, 2)``.

    Updates ``state`` to the last sample; returns what the signals are made from.
    """
    piezo, z = nm[:, :2], nm[:, 2]
    contact = z <= 0.0
    ds, motion = _motion(piezo, contact, state)
    k = model.lever.spring_constant
    moved = np.any(motion != 0.0, axis=1)
    f_fric = -np.where(contact & moved, world.mu_ts * (k * np.maximum(-z, 0.0) + world.f_ts), 0.0)[:, None] * motion
    sn, sl = model.bar_signals(f_fric, np.maximum(-z, 0.0))
    tip = piezo + model.tip_offset(sn, sl) - off
    h_obs = world.obstacle_heights(tip[:, 0], tip[:, 1])
    force = f_fric.copy()
    defl = np.maximum(h_obs - z, 0.0)
    n, i, version = len(z), 0, None
    margin = max_step + world.release + 2.0 * model.lever.c2 * world.max_height / model.lever.normal_gain + 1.0
    while i < n:
        if version != world.version:
            slow, h_obj = _classify(world, tip[i:], z[i:], contact[i:], margin)
            base, version = i, world.version
        s = slow[i - base]
        j = i + 1
        while j < n and slow[j - base] == s:
            j += 1
        if s:
            _slow_run(world, model, piezo, z, off, ds, f_fric, h_obs, state, i, j, margin, defl, force, tip)
        else:
            if world.episodes:
                world.end_all()
            defl[i:j] = np.maximum(np.maximum(h_obs[i:j], h_obj[i - base:j - base]) - z[i:j], 0.0)
            sn, sl = model.bar_signals(f_fric[i:j], defl[i:j])
            tip[i:j] = piezo[i:j] + model.tip_offset(sn, sl) - off[i:j]
            state.tip = (float(tip[j - 1, 0]), float(tip[j - 1, 1]))
            state.sl_bar, state.ride = float(sl[-1]), 0.0
        i = j
    state.piezo = piezo[-1].copy()
    state.z = float(z[-1])
    state.motion = motion[-1].copy()
    state.force = force[-1].copy()
    return Played(defl, force, tip)


def _motion(piezo: np.ndarray, contact: np.ndarray, state: TipState) -> tuple[np.ndarray, np.ndarray]:
    """``(ds, motion)``: piezo step length (nm) per sample and the unit direction of the
    lateral force. In contact the direction of the last step is held while the piezo
    stands still between DAC codes (static friction keeps the lever twisted); lifted, 0."""
    prev = np.vstack([state.piezo[None, :], piezo[:-1]])
    step = piezo - prev
    ds = np.hypot(step[:, 0], step[:, 1])
    unit = np.where(ds[:, None] > 0, step / np.where(ds > 0, ds, 1.0)[:, None], 0.0)
    unit[~contact] = 0.0
    event = (ds > 0) | ~contact
    last = np.maximum.accumulate(np.where(event, np.arange(ds.size), -1))
    motion = np.where((last >= 0)[:, None], unit[np.maximum(last, 0)], state.motion[None, :])
    return ds, motion


def _classify(world: PushPhysics, tip: np.ndarray, z: np.ndarray, contact: np.ndarray,
              margin: float) -> tuple[np.ndarray, np.ndarray]:
    """``(slow, h_obj)``: which samples need the physics, and the apex height over objects
    for the lifted ones that graze an object."""
    n = len(z)
    slow, h_obj = np.zeros(n, bool), np.zeros(n)
    low = contact | (z < world.max_height)
    if not low.any():
        return slow, h_obj
    idx = np.flatnonzero(low)
    pts = tip[idx]
    reach = world.tip_radius + margin
    cands = world.candidates(pts.min(axis=0), pts.max(axis=0), reach)
    if cands.size == 0:
        return slow, h_obj
    units = np.flatnonzero(np.isin(world.contacts.groups, cands))
    gap = world.unit_gaps(units, pts[:, 0], pts[:, 1])
    slow[idx] = contact[idx] & (gap < reach)
    lifted = idx[~contact[idx]]
    if lifted.size:
        h_obj[lifted] = world.unit_heights(units, tip[lifted, 0], tip[lifted, 1])
    return slow, h_obj


def _slow_run(world: PushPhysics, model: SignalModel, piezo, z, off, ds, f_fric, h_obs,
              state: TipState, i: int, j: int, margin: float, defl, force, tip) -> None:
    """Samples ``i:j`` one by one through the pushing physics (results written in place).
    The tip is deflected by the lever's normal load and by the twist of the lateral force
    at the sample before (S̄_l = F_y / (k_l K_l / h), eq. 3.9). The part (h/l) F_x of S̄_n
    (eq. 3.6) reaches the signals (:meth:`SignalModel.bar_signals`) but not the tip's
    place here: about 1 nm at 40 nN, it closed a loop with a blocked object's stiffness
    (``lateral_gain / C1``) of gain near 1, and rods pushed in the bundled bowtie were lost
    (10 seeds: 56 of 70 slots against 62 without it)."""
    lever = model.lever
    (m00, m01), (m10, m11) = model.offset_matrix
    r10, r11 = _rotation_row(model.psi)
    kn, lg, k = lever.normal_gain, lever.lateral_gain, lever.spring_constant
    lo, hi = tip[i:j].min(axis=0), tip[i:j].max(axis=0)
    cands = world.candidates(lo, hi, world.tip_radius + margin)
    p0, sl, ride = state.tip, state.sl_bar, state.ride
    z_prev = z[i - 1] if i > 0 else state.z
    held = force[i - 1].copy() if i > 0 else state.force.copy()
    for q in range(i, j):
        sn = (max(ride, h_obs[q]) - z[q]) / kn
        p1 = (piezo[q, 0] + m00 * sn + m01 * sl - off[q, 0], piezo[q, 1] + m10 * sn + m11 * sl - off[q, 1])
        theta = world.half_angle + twist_deg(sl, lever)
        lifting = z[q] > z_prev
        pushing, f, h = world.step(cands, p0, p1, k * -z[q], theta, lifting=lifting,
                                   lag=(m01 * sl, m11 * sl))
        z_prev = z[q]
        defl[q] = max(max(h, h_obs[q]) - z[q], 0.0)
        if pushing:
            force[q] = f
        elif ds[q] == 0.0 and not lifting:      # between DAC codes: the lever stays twisted
            force[q] = held
        else:
            force[q] = f_fric[q]
        held = force[q]
        sl = (r10 * held[0] + r11 * held[1]) / lg
        ride = h
        tip[q] = p1
        p0 = p1
    state.tip, state.sl_bar, state.ride = p0, sl, ride


def _rotation_row(psi: float) -> tuple[float, float]:
    """Second row of R(ψ) (eq. 3.7): the cantilever-frame y of an AFM-frame vector."""
    c, s = math.cos(math.radians(psi)), math.sin(math.radians(psi))
    return -s, -c


class MoveTracker:
    """Registers the scanner's XY moves with the creep model.

    While XY moves, every ``max(min_step, MIN_PIECE)`` of displacement from where the
    last recorded move ended (at least ``MIN_PIECE_TIME`` after it) is recorded as a move
    at the sample that reaches it
    (:func:`nanoasm.drift.creep.creep_moves`): creep is linear in the step, so a motion
    creeps as the superposition of its pieces, each from its own time, and a slow push
    of many seconds (or legs one after another) creeps as it goes rather than from its end.
    The moves of a chunk are recorded before it is played, so a piece creeps from its own
    sample on. A move also ends when XY stays on one DAC code for ``stop_samples``
    samples; it is recorded at that sample as the step from where the last *recorded*
    move ended. A move shorter than
    ``[creep] min_step`` is not recorded and does not restart the chain: its
    displacement is carried into the next move, so every displacement creeps (creep is
    linear in the step) and only its attribution time is coarsened.

    A chunk that ends while XY is still moving leaves the move open; if the next chunk or
    scan line comes after a pause (a mode switch, a settle), XY was at rest through it,
    so the move is recorded where and ``stop_samples`` after XY stopped, not when the
    instrument acts again (a 2 s mode switch would otherwise start its creep late).
    """

    def __init__(self, drift: DriftModel, start_xy: np.ndarray, stop_samples: int):
        self.drift = drift
        self.start = np.asarray(start_xy, float).copy()
        self.stop = max(1, int(stop_samples))
        self.still = 0
        self.rest: tuple[float, float, np.ndarray] | None = None   # last sample: (t, period, xy)

    def jump(self, t: float, xy: np.ndarray) -> None:
        """The instrument itself took XY to ``xy`` at ``t`` (a scan line): the move from
        where the last one ended is recorded now, and XY counts as at rest there."""
        self._settle(float(t))
        self._end(float(t), np.asarray(xy, float))
        self.still = self.stop
        self.rest = None

    def _settle(self, t_next: float) -> None:
        """Before acting again at ``t_next``: an open move whose XY stopped with the last
        chunk ended ``stop_samples`` after that, if the pause was as long."""
        if self.rest is None or self.still >= self.stop:
            return
        t_last, period, xy = self.rest
        t_end = t_last + (self.stop - self.still) * period
        if t_next > t_end + 0.5 * period:
            self._end(t_end, xy)
            self.still = self.stop

    def _end(self, t: float, xy: np.ndarray) -> bool:
        d = xy - self.start
        if self.drift.record_move(t, float(d[0]), float(d[1])):
            self.start = xy.copy()
            return True
        return False

    def track(self, nm: np.ndarray, codes: np.ndarray, previous: np.ndarray, t: np.ndarray) -> None:
        """Samples ``codes`` (their nm ``nm`` and times ``t``) about to be played after
        ``previous``: the moves they make are recorded before they are played, so each
        creeps from its own sample on (:func:`nanoasm.drift.creep.creep_moves`)."""
        period = float(t[1] - t[0]) if t.size > 1 else (self.rest[1] if self.rest is not None else 0.0)
        if period > 0.0:
            self._settle(float(t[0]) - period)
        prev = np.vstack([previous[None, :2], codes[:-1, :2]])
        still = np.all(codes[:, :2] == prev, axis=1)
        idx = np.arange(still.size)
        last_move = np.maximum.accumulate(np.where(still, -1, idx))
        count = np.where(last_move >= 0, idx - last_move, idx + 1 + self.still)
        if self.drift.creep_params.amplitude > 0:
            rests = np.flatnonzero(count == self.stop)
            for k in creep_moves(self.start, nm[:, :2], t, self.drift.creep_params.min_step,
                                 self.drift.last_move, rests):
                self._end(float(t[k]), nm[k, :2])
        self.still = int(count[-1])
        if period > 0.0:
            self.rest = (float(t[-1]), period, nm[-1, :2].copy())
