"""A calibration specimen under the simulated instrument's lever (seed 3.4-3.6).

The seed calibrates its lever on samples made for it: a force curve on hard glass
(§3.4.2), friction loops on a tilted glass surface (§3.4.3), lines at several loads
against a fixed mark (§3.6.4). :class:`CalibrationAFM` is an
:class:`~nanoasm.instrument.Instrument` over such a specimen, with the lever, detector,
friction, adhesion, scanner and drift of a world (the same
:class:`~nanoasm.world.sim.signals.SignalModel` as :class:`~nanoasm.world.sim.SimulatedAFM`,
so its free-air baselines are the run's), holding, about the scanner's centre in the
lever's frame (``a`` along the lever axis, ``b`` along its y axis, eq. 3.7):

- a flat, hard substrate of the world's material (force curve and friction loop at
  ``a = -1500`` nm);
- a ramp tilted by ``tilt`` (20° by default) rising along ``b`` over ``|a| <= 300`` nm, its
  top at most 0.6 of the lift height, then a short plateau;
- a step of ``step`` nm (at most 0.3 of the lift) over ``a >= 1000`` nm, its edge across
  the lever axis.

Per DAC sample (vectorised), the piezo following the DAC through the amplifier's low-pass
(``[sim] piezo_tau``): the tip sits at ``piezo + R(ψ)⁻¹ (C2 S̄n, C1 S̄l)`` (eq.
3.30-3.34) less the drift; it presses ``d = max(h - z, 0)`` nm into the surface of height
``h`` under it, taken as the lower of the heights under the tip deflected by the flat
and by the climbed deflection (a tip climbs a step once the climbed lever still puts it
on top); sliding, the surface pushes back with :func:`~.calibration.slope_friction`
(friction μ_ts (N + F^a_ts)), and the detector reads it as
:meth:`SignalModel.raw` does. Not modelled: creep, tip shape, adhesion hysteresis,
faults. For dry-runs and tests, as the simulated AFM is.
"""

from __future__ import annotations

import math

import numpy as np

from nanoasm.errors import InstrumentLimitError
from nanoasm.instrument import HeightImage, Region, SignalBlock, ramp
from nanoasm.world.cantilever import to_afm
from nanoasm.world.params import WorldParams

from .calibration import slope_friction
from .clock import InstrumentClock
from .drift_model import DriftModel
from .instrument_base import SimulatedInstrument
from .signals import SignalModel
from .stream import TipState, _motion

#: Where the specimen's features lie about the scanner's centre, lever frame (a, b), nm.
SUBSTRATE_A = -1500.0
RAMP_HALF_WIDTH, RAMP_LENGTH, RAMP_PLATEAU = 300.0, 600.0, 200.0
STEP_A, STEP_WIDTH, STEP_HALF_LENGTH = 1000.0, 1000.0, 500.0


class CalibrationAFM(SimulatedInstrument):
    """A simulated instrument over a calibration specimen (see the module docstring).

    Parameters
    ----------
    params : WorldParams
        The world whose lever, detector, friction, adhesion, scanner and drift it has.
    model : SignalModel, optional
        The detector model; default that of a scene of the scanner's whole range.
    seed : int
        Seed of the noise and drift.
    tilt : float
        Slope of the ramp, degrees.
    """

    def __init__(self, params: WorldParams, *, model: SignalModel | None = None, seed: int = 0,
                 tilt: float = 20.0):
        if not 0.0 < tilt < 60.0:
            raise ValueError(f"tilt must lie in (0, 60) degrees, got {tilt!r}")
        self.params = params
        cfg = params.scanner
        self._model = model or SignalModel.from_params(params, 0.0, cfg.xy_range[0])
        noise, drift = (np.random.default_rng(s) for s in np.random.SeedSequence([seed, 23]).spawn(2))
        self._rng = noise
        self._clock = InstrumentClock(params.timing)
        self._drift = DriftModel(params.drift, params.creep, drift, change=params.drift_change)
        psi = cfg.scan_angle
        self.u = to_afm(np.array([1.0, 0.0]), psi)          # the lever axis, AFM frame
        self.v = to_afm(np.array([0.0, 1.0]), psi)          # the lever's y axis
        self.centre = 0.5 * np.asarray(cfg.xy_range, float)
        self.tan = math.tan(math.radians(tilt))
        self.ramp_length = min(RAMP_LENGTH, 0.6 * cfg.lift / self.tan)
        self.step = min(50.0, 0.3 * cfg.lift)
        self.mu = params.friction.mu_ts
        self.shear = params.friction.mu_ts * params.adhesion.tip_substrate
        self._last = cfg.rest_codes()
        rest = cfg.codes_to_nm(self._last)
        self._state = TipState(rest[:2].copy(), (float(rest[0]), float(rest[1])), float(rest[2]))
        self._piezo = rest[:2].copy()                 # where the low-passed piezo is
        self._signals = (0.0, 0.0)

    @classmethod
    def beside(cls, sim, seed: int, tilt: float = 20.0) -> CalibrationAFM:
        """The specimen under the lever and detector of the simulated AFM ``sim``."""
        return cls(sim.params, model=sim._model, seed=seed, tilt=tilt)

    # -- where things are ------------------------------------------------------------------
    def point(self, a: float, b: float) -> tuple[float, float]:
        """Scanner nm of lever-frame coordinates (a, b) about the centre, at the start."""
        p = self.centre + a * self.u + b * self.v
        return float(p[0]), float(p[1])

    def sites(self) -> dict[str, tuple]:
        """Where the specimen's features are (scanner nm at the start): ``substrate`` (a
        point), ``flat`` (a line along the lever's y axis on the substrate), ``slope`` (a
        line up the ramp), ``edge`` (a line along the lever axis onto the step)."""
        r = self.ramp_length
        return {"substrate": self.point(SUBSTRATE_A, -500.0),
                "flat": (self.point(SUBSTRATE_A, -500.0), self.point(SUBSTRATE_A, 500.0)),
                "slope": (self.point(0.0, 0.1 * r), self.point(0.0, 0.9 * r)),
                "edge": (self.point(STEP_A - 350.0, 0.0), self.point(STEP_A + 150.0, 0.0))}

    def heights(self, xy: np.ndarray) -> np.ndarray:
        """Surface height (nm) at sample-frame points ``(n, 2)``."""
        rel = np.asarray(xy, float) - self.centre
        a, b = rel @ self.u, rel @ self.v
        r = self.ramp_length
        on_ramp = (np.abs(a) <= RAMP_HALF_WIDTH) & (b >= 0.0) & (b <= r + RAMP_PLATEAU)
        h = np.where(on_ramp, self.tan * np.clip(b, 0.0, r), 0.0)
        on_step = (a >= STEP_A) & (a <= STEP_A + STEP_WIDTH) & (np.abs(b) <= STEP_HALF_LENGTH)
        return np.where(on_step, self.step, h)

    def _slope_along(self, xy: np.ndarray, motion: np.ndarray) -> np.ndarray:
        """tan of the surface's slope along the unit ``motion`` at sample points ``xy``."""
        rel = np.asarray(xy, float) - self.centre
        a, b = rel @ self.u, rel @ self.v
        on = (np.abs(a) <= RAMP_HALF_WIDTH) & (b >= 0.0) & (b <= self.ramp_length)
        return np.where(on, self.tan * (motion @ self.v), 0.0)

    # -- the Instrument protocol (config, clock, ledger, signals, position, write: the base's) -----
    def _play(self, codes: np.ndarray) -> SignalBlock:
        cfg, model, k = self.config, self._model, self._model.lever.spring_constant
        nm = cfg.codes_to_nm(codes)
        nm[:, :2] = self._smooth(nm[:, :2])
        n = nm.shape[0]
        t = self._clock.now + np.arange(1, n + 1) / cfg.sample_rate
        off = np.stack(self._drift.offset(t), axis=-1)
        piezo, z = nm[:, :2], nm[:, 2]
        base = piezo - off                       # the undeflected tip, sample frame

        def pressed(defl):
            """The tip and the surface under it, the lever deflected by ``defl``."""
            tip = base + model.tip_offset(defl / model.lever.normal_gain, np.zeros(n))
            return tip, self.heights(tip)

        tip, h_flat = pressed(np.maximum(-z, 0.0))
        _, h_climbed = pressed(np.maximum(h_flat - z, 0.0))
        h = np.minimum(h_flat, h_climbed)
        defl = np.maximum(h - z, 0.0)
        _, motion = _motion(piezo, z <= h, self._state)
        moving = np.any(motion != 0.0, axis=1)
        f_lat = np.where(moving, slope_friction(k * defl, self._slope_along(tip, motion), self.mu, self.shear), 0.0)
        sn_bar, sl_bar = model.bar_signals(-f_lat[:, None] * motion, defl)
        s_n, s_l = model.raw(sn_bar, sl_bar, piezo[:, 0], z + defl, self._rng)
        contact = int(np.count_nonzero(defl > 0))
        self._clock.samples(contact, cfg.sample_rate, "push")
        self._clock.samples(n - contact, cfg.sample_rate, "travel")
        self._state.piezo, self._state.z, self._state.motion = piezo[-1].copy(), float(z[-1]), motion[-1].copy()
        self._last = codes[-1].copy()
        self._signals = (float(s_n[-1]), float(s_l[-1]))
        return SignalBlock(t, s_n, s_l)

    def scan_line(self, a: tuple[float, float], b: tuple[float, float], n: int) -> np.ndarray:
        """Heights (nm) at ``n`` points from ``a`` to ``b`` (tapping mode); ends lifted at ``b``."""
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 2:
            raise ValueError(f"n must be an integer of at least 2, got {n!r}")
        pa, pb = self._inside("a", a), self._inside("b", b)
        off = np.asarray(self._drift.offset(self._clock.now), float)
        pts = pa + np.linspace(0.0, 1.0, int(n))[:, None] * (pb - pa) - off
        heights = self.heights(pts) + self._rng.normal(0.0, self.params.noise.height_rms, int(n))
        self._clock.scan_line(int(n))
        self._move_lifted(pb)
        return heights

    def full_scan(self, pixels: int, region: Region | None = None) -> HeightImage:
        """A ``pixels`` x ``pixels`` topography of the square at the region's lower-left
        corner (default: 5 µm about the centre); ends lifted where it started."""
        if isinstance(pixels, bool) or not isinstance(pixels, (int, np.integer)) or pixels < 2:
            raise ValueError(f"pixels must be an integer of at least 2, got {pixels!r}")
        x0, y0, x1, y1 = region if region is not None else (*(self.centre - 2500.0), *(self.centre + 2500.0))
        self._inside("region corner", (x0, y0))
        self._inside("region corner", (x1, y1))
        side = max(x1 - x0, y1 - y0)
        px = side / int(pixels)
        c = (np.arange(int(pixels)) + 0.5) * px
        xx, yy = np.meshgrid(x0 + c, y0 + c)
        off = np.asarray(self._drift.offset(self._clock.now), float)
        pts = np.stack([xx.ravel(), yy.ravel()], axis=-1) - off
        h = self.heights(pts).reshape(xx.shape) + self._rng.normal(0.0, self.params.noise.height_rms, xx.shape)
        self._clock.full_scan(int(pixels))
        return HeightImage(h, px, (float(x0), float(y0)), "simulated calibration specimen")

    def park(self) -> None:
        """Lift to the top of Z, then move XY to rest, within the slew limit."""
        cfg = self.config
        rest = cfg.rest_codes()
        up = self._last.copy()
        up[2] = rest[2]
        codes = np.vstack([ramp(self._last, up, cfg), ramp(up, rest, cfg)])
        if codes.shape[0]:
            self._play(codes)

    # -- helpers -------------------------------------------------------------------------------
    def _smooth(self, xy: np.ndarray) -> np.ndarray:
        """The piezo follows the DAC through the amplifier's low-pass (``[sim] piezo_tau``),
        as on the simulated AFM: a diagonal path's single-axis code steps blur into the line."""
        from scipy.signal import lfilter

        a = 1.0 - math.exp(-1.0 / (self.params.sim.piezo_tau * self.config.sample_rate))
        out = np.empty_like(xy)
        for k in range(2):
            out[:, k], _ = lfilter([a], [1.0, a - 1.0], xy[:, k], zi=[(1.0 - a) * self._piezo[k]])
        self._piezo = out[-1].copy()
        return out

    def _inside(self, name: str, p) -> np.ndarray:
        arr = np.asarray(p, float)
        if arr.shape != (2,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} must be two finite numbers, got {p!r}")
        if np.any(arr < self.config.lower[:2]) or np.any(arr > self.config.upper[:2]):
            raise InstrumentLimitError(f"{name} = ({arr[0]:g}, {arr[1]:g}) nm lies outside the scanner range; "
                                       "nothing scanned")
        return arr

    def _move_lifted(self, xy: np.ndarray) -> None:
        """After a scan line the DAC is at its end, lifted (as the simulated AFM leaves it)."""
        cfg = self.config
        self._last = cfg.nm_to_codes(np.array([xy[0], xy[1], cfg.lift]))
        self._state.piezo, self._state.z = np.asarray(xy, float).copy(), cfg.lift
        self._state.motion = np.zeros(2)
        self._piezo = np.asarray(xy, float).copy()
