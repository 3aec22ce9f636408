"""The simulated AFM: an :class:`~nanoasm.instrument.Instrument` over a scene's truth.

:class:`SimulatedAFM` is a first-class instrument (ophyd's simulated devices): the
executor drives it exactly as it drives hardware, through ``write``, ``full_scan``,
``scan_line``, ``signals``, ``clock`` and ``park``, and cannot tell the two apart.

Frames. The *sample frame* is the scene's (and the layout's) frame. The *scanner frame*
is the DAC's (see :mod:`nanoasm.instrument`): a sample point ``p`` lies under the
scanner position ``p + d(t)``, ``d`` the drift offset of
:class:`~nanoasm.world.sim.drift_model.DriftModel` (zero at the clock's start time, 0 unless
given, before the run's first scan; it follows the world's ``[drift]``, ``[drift_change]`` and
``[creep]``). The deflected tip sits at ``piezo + R(ψ)⁻¹ δ`` (eq. 3.30-3.34).

Contact rule. The tip touches the substrate when the commanded ``z ≤ 0`` (``z = -preload``
while pushing); the lever then presses with ``k (H - z)`` nN, H the height of what the
apex rests on (0 on the substrate). A lifted tip (``z > 0``) moves nothing; it grazes
(deflects over) an object taller than ``z``.

Randomness. One seed (``seed``, else the scene's ``seed``) feeds independent streams for
the objects' truth, faults, van der Waals errors, drift, the substrate, scan noise and
signal noise, so the same seed and the same commands reproduce a run bit for bit, and
scanning more or less never changes the physics. With neither seed, fresh entropy
(kept in ``seed``, so the run can be repeated).

Time. Every call charges the instrument clock (:class:`InstrumentClock` ledger): streamed
samples at ``sample_rate`` (``push`` in contact, ``travel`` lifted), full scans
(``full_scan_line`` per line), scan lines (``local_scan``), a mode switch between
tapping (scans) and contact (pushes) to the activity that needs it.

:meth:`SimulatedAFM.truth` and :meth:`SimulatedAFM.diagnostics` expose the simulated
truth for dry-run reports and tests only: executor code must never call them.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from nanoasm.bodies import Body
from nanoasm.errors import InstrumentLimitError
from nanoasm.instrument import HeightImage, Region, SignalBlock, ramp
from nanoasm.world.params import WorldParams
from nanoasm.world.render import make_surface, render_line, render_scan, surface_near
from nanoasm.world.scene import Scene

from .calibration import (
    ForceCurve,
    FrictionLoop,
    force_curve_signals,
    friction_loop_signals,
)
from .clock import InstrumentClock
from .drift_model import DriftModel
from .instrument_base import SimulatedInstrument
from .objects import build_objects
from .push import PushPhysics
from .signals import SignalModel
from .stream import MoveTracker, TipState, play_chunk


TAPPING, CONTACT = "tapping", "contact"
_STREAMS = ("truth", "faults", "vdw", "drift", "surface", "scan", "signal")


class PlacedDrift:
    """The drift model seen from the scanner: a sample point ``p`` appears at
    ``p + placement + drift.offset(t)``."""

    def __init__(self, drift: DriftModel, placement: tuple[float, float]):
        self.drift = drift
        self.placement = placement

    def offset(self, t):
        dx, dy = self.drift.offset(t)
        return dx + self.placement[0], dy + self.placement[1]

    @property
    def creep_params(self):
        return self.drift.creep_params

    @property
    def last_move(self) -> float:
        return self.drift.last_move

    def record_move(self, t: float, dx: float, dy: float) -> bool:
        return self.drift.record_move(t, dx, dy)


class SimulatedAFM(SimulatedInstrument):
    """A simulated AFM over ``scene`` (see the module docstring for frames, contact, time).

    Parameters
    ----------
    scene : Scene
        The truth: objects, obstacles, and (unless ``params`` is given) the world's tables.
    seed : int, optional
        Seed of every random stream; defaults to ``scene.seed``.
    params : WorldParams, optional
        Physical parameters; defaults to ``scene.params``.
    placement : (x, y), optional
        Where the scene's origin lies in the scanner frame at the start (nm); by default
        the scene is centred in the scanner's XY range.
    start_time : float
        Instrument time (s) of the clock at the start, e.g. an instrument that counts
        from its boot; the world does the same from any start.
    """

    def __init__(self, scene: Scene, *, seed: int | None = None, params: WorldParams | None = None,
                 placement: tuple[float, float] | None = None, start_time: float = 0.0):
        self.scene = scene
        self.params = scene.params if params is None else params
        if not isinstance(self.params, WorldParams):
            raise TypeError(f"params must be a WorldParams, got {type(self.params).__name__}")
        cfg = self.params.scanner
        if scene.area[0] > cfg.xy_range[0] or scene.area[1] > cfg.xy_range[1]:
            raise ValueError(f"scene area {scene.area[0]:g} x {scene.area[1]:g} nm exceeds the scanner's "
                             f"XY range {cfg.xy_range[0]:g} x {cfg.xy_range[1]:g} nm")
        ss = np.random.SeedSequence(scene.seed if seed is None else seed)
        self.seed = ss.entropy          # the seed given, or the fresh entropy drawn: reruns the world
        rng = dict(zip(_STREAMS, (np.random.default_rng(s) for s in ss.spawn(len(_STREAMS)))))
        self._clock = InstrumentClock(self.params.timing, start_time)
        # the sample sits centred under the scanner's range, as a user would place it
        if placement is None:
            placement = (0.5 * (cfg.xy_range[0] - scene.area[0]), 0.5 * (cfg.xy_range[1] - scene.area[1]))
        self.placement = (float(placement[0]), float(placement[1]))
        self._drift = PlacedDrift(DriftModel(self.params.drift, self.params.creep, rng["drift"],
                                             epoch=self._clock.now, change=self.params.drift_change),
                                  self.placement)
        table, units, groups, wires = build_objects(scene.objects, self.params, rng["truth"])
        self._world = PushPhysics(table, units, groups, wires, self.params, scene.obstacles,
                                  rng["faults"], rng["vdw"])
        self._surface = make_surface((), scene.obstacles, scene.area, roughness_rms=self.params.sim.roughness_rms,
                                     roughness_length=self.params.sim.roughness_length, rng=rng["surface"])
        # the piezo-bow baseline B rises across the sample's area (seed Fig. 3.14)
        self._model = SignalModel.from_params(self.params, self.placement[0], scene.area[0])
        self._rng_scan, self._rng_signal = rng["scan"], rng["signal"]
        self._last = cfg.rest_codes()
        rest = cfg.codes_to_nm(self._last)
        self._piezo_xy = rest[:2].copy()
        self._state = TipState(rest[:2].copy(), (float(rest[0]), float(rest[1])), float(rest[2]))
        self._mode = TAPPING
        # the first full scan's rows for the harness (never the executor's to read): start
        # time, its region's lower edge (scanner nm), pixel size, line time, lines
        self.first_scan: tuple[float, float, float, float, int] | None = None
        self._moves = MoveTracker(self._drift, rest[:2], round(self.params.sim.stop_time * cfg.sample_rate))
        a, b = self._model.baselines(np.array([rest[0]]), np.array([rest[2]]))
        self._signals = (float(a[0]), float(b[0]))

    # -- the Instrument protocol (config, clock, ledger, signals, position, write: the base's) -----
    def _play(self, codes: np.ndarray, activity: str | None = None) -> SignalBlock:
        """Play checked codes: sample ``k`` plays at ``clock() + (k + 1) / sample_rate`` (after
        a 2 s mode switch if it is the first contact after a scan)."""
        cfg = self.config
        nm = cfg.codes_to_nm(codes)
        nm[:, :2] = self._smooth(nm[:, :2])
        n = nm.shape[0]
        n_contact = int(np.count_nonzero(nm[:, 2] <= 0.0))
        if n_contact and self._mode != CONTACT:
            self._clock.mode_switch(activity or "push")
            self._mode = CONTACT
        t = self._clock.now + np.arange(1, n + 1) / cfg.sample_rate
        self._moves.track(nm, codes, self._last, t)     # each move creeps from its own sample
        off = np.stack(self._drift.offset(t), axis=-1)
        played = play_chunk(self._world, self._model, nm, off, self._state, cfg.max_step)
        sn_bar, sl_bar = self._model.bar_signals(played.force, played.deflection)
        s_n, s_l = self._model.raw(sn_bar, sl_bar, nm[:, 0], nm[:, 2] + played.deflection,
                                   self._rng_signal)
        if activity is None:
            self._clock.samples(n_contact, cfg.sample_rate, "push")
            self._clock.samples(n - n_contact, cfg.sample_rate, "travel")
        else:
            self._clock.samples(n, cfg.sample_rate, activity)
        self._last = codes[-1].copy()
        self._signals = (float(s_n[-1]), float(s_l[-1]))
        return SignalBlock(t, s_n, s_l)

    def full_scan(self, pixels: int, region: Region | None = None) -> HeightImage:
        """A ``pixels`` x ``pixels`` scan of the square of side max(width, height) anchored at
        the region's lower-left corner (default: the scene's area); line ``i`` is
        acquired at ``t0 + i × full_scan_line`` and drawn with the drift of that time."""
        if isinstance(pixels, bool) or not isinstance(pixels, (int, np.integer)) or pixels < 2:
            raise ValueError(f"pixels must be an integer of at least 2, got {pixels!r}")
        x0, y0, x1, y1 = self._region(region)
        side = max(x1 - x0, y1 - y0)
        self._to_tapping("full_scan")
        timing = self.params.timing
        if self.first_scan is None:
            self.first_scan = (self._clock.now, y0, side / int(pixels), timing.full_scan_line, int(pixels))
        image = render_scan(self._surface_now(), side / int(pixels), tip=self._world.tip,
                            window=(x0, y0, side, side), noise_rms=self.params.noise.height_rms,
                            line_offset_prob=self.params.sim.line_offset_prob,
                            line_offset_rms=self.params.sim.line_offset_rms,
                            drift=self._sample_shift, line_time=timing.full_scan_line,
                            t0=self._clock.now, rng=self._rng_scan)
        self._clock.full_scan(int(pixels))
        self._lift_in_place()
        return image

    def scan_line(self, a: tuple[float, float], b: tuple[float, float], n: int) -> np.ndarray:
        """Heights (nm) at ``n`` points from ``a`` to ``b`` (scanner frame), tapping mode, all
        with the drift of the present time; the DAC is left at ``b``, lifted."""
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 2:
            raise ValueError(f"n must be an integer of at least 2, got {n!r}")
        pa, pb = self._point("a", a), self._point("b", b)
        self._to_tapping("local_scan")
        t = self._clock.now
        dx, dy = self._drift.offset(t)
        self._moves.jump(t, pa)          # whatever moved the DAC here, then on to a
        sa, sb = (pa[0] - dx, pa[1] - dy), (pb[0] - dx, pb[1] - dy)
        # the bodies near the line alone: one array test, not a loop over every body
        near = surface_near(self._surface_now(), self._world.contacts.cores(), np.minimum(sa, sb),
                            np.maximum(sa, sb), tip=self._world.tip)
        heights = render_line(near, sa, sb, int(n), tip=self._world.tip, noise_rms=self.params.noise.height_rms,
                              rng=self._rng_scan)
        self._clock.scan_line(int(n))
        self._moves.jump(self._clock.now, pb)
        # the DAC is left at the line's end, lifted (the next line of a pattern starts close by)
        end = self.config.nm_to_codes(np.array([pb[0], pb[1], self.config.lift]))
        self._last = end
        self._piezo_xy = pb.copy()
        self._lift_in_place()
        return heights

    def park(self) -> None:
        """Lift the tip to the top of Z, then move XY to the rest position (charged as travel)."""
        cfg = self.config
        rest = cfg.rest_codes()
        up = self._last.copy()
        up[2] = rest[2]
        codes = np.vstack([ramp(self._last, up, cfg), ramp(up, rest, cfg)])
        if codes.shape[0]:
            self._play(codes, "travel")
        self._world.end_all()

    # -- calibration experiments (seed 3.4) -------------------------------------------------------
    def force_curve(self, z_top: float = 200.0, depth: float | None = None, n: int = 400) -> ForceCurve:
        """Approach the substrate at the current XY from ``z_top`` nm to ``-depth`` nm
        (default twice the preload) and retract, ``n`` samples each way; charged as ``push``."""
        depth = 2.0 * self.config.preload if depth is None else float(depth)
        if not (z_top > 0 and depth > 0 and n >= 4):
            raise ValueError("force_curve needs z_top > 0, depth > 0 and n >= 4")
        x = float(self.config.codes_to_nm(self._last)[0])
        curve = force_curve_signals(self._model, self.params, x, float(z_top), depth, int(n), self._rng_signal)
        self._clock.samples(2 * int(n), self.config.sample_rate, "push")
        self._lift_in_place()
        return curve

    def friction_loop(self, tilt_deg: float, loads=None, width: float = 1000.0, n: int = 200) -> FrictionLoop:
        """Trace/retrace S_l on a calibration surface tilted by ``tilt_deg`` at each load
        (nN; default 2-30 nN), lines of ``n`` samples over ``width`` nm; charged as ``push``."""
        if not 0.0 < tilt_deg < 90.0:
            raise ValueError(f"tilt_deg must lie in (0, 90), got {tilt_deg!r}")
        loads = np.linspace(2.0, 30.0, 8) if loads is None else np.asarray(loads, float)
        if loads.ndim != 1 or loads.size < 2 or not np.all(np.isfinite(loads)) or np.any(loads <= 0):
            raise ValueError("loads must be at least two positive forces in nN")
        x = float(self.config.codes_to_nm(self._last)[0])
        loop = friction_loop_signals(self._model, self.params, x, float(tilt_deg), loads, float(width),
                                     int(n), self._rng_signal)
        self._clock.samples(2 * loads.size * int(n), self.config.sample_rate, "push")
        self._lift_in_place()
        return loop

    # -- truth, for dry-run reports and tests only -------------------------------------------------
    def truth(self) -> tuple[Body, ...]:
        """Every object's true pose in the sample frame, with the scene's ids (a wire as
        the rod on its end-to-end chord). For dry-run reports and tests ONLY: executor
        code must never call it (a real instrument has no such method)."""
        return self._world.truth()

    def true_offset(self, t: float) -> tuple[float, float]:
        """Where a sample point appears shifted in the scanner frame at instrument time ``t``
        (nm): the sample's placement plus the drift. For dry-run reports and tests ONLY (it
        is how the report puts the truth into the frame of the run's first full scan)."""
        return self._drift.offset(float(t))

    def footprints(self) -> tuple[Body, ...]:
        """Every contact footprint (a wire's segments as rods with ids ``"<id>#<k>"``): what
        a scan images. For dry-run reports and tests only."""
        return self._world.unit_bodies()

    def diagnostics(self) -> dict:
        """Counters of the simulation (pushes that moved something, slips, bluntings, physics
        steps: samples played through the pushing physics) and the current tip radius.
        For dry-run reports and tests only."""
        w = self._world
        return {"pushes": w.pushes, "slips": w.slips, "blunted": w.blunted, "steps": w.steps,
                "tip_radius": w.tip_radius}

    # -- persistence (a dry-run kept beside its log) --------------------------------------------------
    def state_dict(self) -> dict:
        """Everything the world holds that changes as it runs, as JSON types: parameters,
        seed, objects, pushes in progress, clock, tip, drift's moves, random generators'
        states (:mod:`nanoasm.world.sim.state`)."""
        from .state import sim_state

        return sim_state(self)

    @classmethod
    def from_state(cls, scene: Scene, state: dict) -> SimulatedAFM:
        """The simulated AFM over ``scene`` as :meth:`state_dict` gave it; every field is
        checked and a bad one, or a state of another scene, raises ``ValueError`` naming
        its key."""
        from .state import sim_from_state

        return sim_from_state(scene, state)

    # -- helpers -----------------------------------------------------------------------------------
    def _smooth(self, xy: np.ndarray) -> np.ndarray:
        """The piezo follows the DAC through its amplifier's first-order low-pass
        (``[sim] piezo_tau``): the single-axis code steps of a diagonal path blur into the line."""
        from scipy.signal import lfilter

        a = 1.0 - math.exp(-1.0 / (self.params.sim.piezo_tau * self.config.sample_rate))
        if self._piezo_xy is None:
            self._piezo_xy = xy[0].copy()
        out = np.empty_like(xy)
        for k in range(2):
            out[:, k], zf = lfilter([a], [1.0, a - 1.0], xy[:, k], zi=[(1.0 - a) * self._piezo_xy[k]])
        self._piezo_xy = out[-1].copy()
        return out

    def _surface_now(self):
        return replace(self._surface, bodies=self._world.unit_bodies())

    def _sample_shift(self, t: np.ndarray) -> np.ndarray:
        """Where the tip at scanner position s touches the sample: s + this (= -offset)."""
        dx, dy = self._drift.offset(t)
        return -np.stack([dx, dy], axis=-1)

    def _to_tapping(self, activity: str) -> None:
        self._world.end_all()
        self._state.sl_bar = self._state.ride = 0.0
        if self._mode != TAPPING:
            self._clock.mode_switch(activity)
            self._mode = TAPPING

    def _lift_in_place(self) -> None:
        """After a scan or calibration the DAC is back on its last XY, lifted."""
        lift = self.config.nm_to_codes(np.array([0.0, 0.0, self.config.lift]))[2]
        self._last[2] = max(self._last[2], lift)
        self._state.z = float(self.config.codes_to_nm(self._last)[2])

    def _region(self, region: Region | None) -> tuple[float, float, float, float]:
        if region is None:
            px, py = self.placement
            return px, py, px + float(self.scene.area[0]), py + float(self.scene.area[1])
        if len(region) != 4 or not all(math.isfinite(v) for v in region):
            raise ValueError(f"region must be four finite numbers (x0, y0, x1, y1), got {region!r}")
        x0, y0, x1, y1 = (float(v) for v in region)
        if not (x1 > x0 and y1 > y0):
            raise ValueError(f"region must have x1 > x0 and y1 > y0, got {region!r}")
        side = max(x1 - x0, y1 - y0)      # the square scanned, as a scanner would
        self._point("region corner", (x0, y0))
        self._point("region corner", (x0 + side, y0 + side))
        return x0, y0, x1, y1

    def _point(self, name: str, p) -> np.ndarray:
        arr = np.asarray(p, float)
        if arr.shape != (2,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} must be two finite numbers, got {p!r}")
        lo, hi = self.config.lower[:2], self.config.upper[:2]
        if np.any(arr < lo) or np.any(arr > hi):
            raise InstrumentLimitError(f"{name} = ({arr[0]:g}, {arr[1]:g}) nm lies outside the scanner range; "
                                       "nothing scanned")
        return arr
