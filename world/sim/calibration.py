"""Calibration experiments of the simulated AFM (seed 3.4): force curves and friction loops.

Both return raw detector signals, as the instrument would, with the analysis the seed
applies to them:

- :class:`ForceCurve`: S_n (and S_l) while the piezo approaches a hard substrate and
  retracts. In contact the deflection follows the piezo, so K_n is the contact slope
  (eq. 3.13); on retract adhesion holds the tip until the lever pulls with the pull-off
  force (JKR: ``pull_off_fraction`` of F^a_ts, seed 4.2.1); pressing without lateral
  motion, S_l follows S_n by the cross-talk α (seed 3.5).
- :class:`FrictionLoop`: the tip slides up (trace) and down (retrace) a hard surface
  tilted by θ at several loads F_n. Force balance on the slope (seed eq. 3.14-3.19, with
  the adhesive shear A = ν F^a_ts): uphill N' = (F_n + A sin θ)/(cos θ − μ sin θ) and the
  lever pushes with N' sin θ + (μN' + A) cos θ; downhill N = (F_n − A sin θ)/(cos θ + μ sin θ)
  and N sin θ − (μN + A) cos θ. Their slopes against S_n, after removing α, are the two
  sides of eq. 3.27 (trace) and 3.26 (retrace), which
  :func:`~nanoasm.world.cantilever.calibrate_lateral_gain` solves for (k_l K_l / h, μ).

Forces in nN, lengths in nm, signals in V.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nanoasm.world.cantilever import (
    LateralCalibration,
    calibrate_lateral_gain,
    crosstalk_from_force_curve,
    normal_gain_from_force_curve,
)
from nanoasm.world.params import WorldParams
from nanoasm.world.particle_push import adhesion_from_pull_off

from .signals import SignalModel


@dataclass(frozen=True, eq=False)
class ForceCurve:
    """Piezo z (nm) and detector signals (V) on approach, then on retract."""

    z_approach: np.ndarray
    sn_approach: np.ndarray
    sl_approach: np.ndarray
    z_retract: np.ndarray
    sn_retract: np.ndarray
    sl_retract: np.ndarray

    def _contact(self) -> np.ndarray:
        return self.z_approach < 0.0

    def normal_gain(self) -> float:
        """K_n (nm/V): the contact slope of the approach (eq. 3.13)."""
        c = self._contact()
        return normal_gain_from_force_curve(self.z_approach[c], self.sn_approach[c])

    def crosstalk(self) -> float:
        """α: slope of S_l against S_n while pressing (seed 3.5)."""
        c = self._contact()
        return crosstalk_from_force_curve(self.sn_approach[c], self.sl_approach[c])

    def pull_off_force(self, spring_constant: float) -> float:
        """Pull-off force (nN): the lever's largest pull before the tip snaps free, from
        the zero-force level (the contact line of the approach at z = 0)."""
        c = self._contact()
        slope, zero = np.polyfit(self.z_approach[c], self.sn_approach[c], 1)
        return float(spring_constant * abs(1.0 / slope) * (zero - self.sn_retract.min()))

    def tip_adhesion(self, spring_constant: float) -> float:
        """F^a_ts (nN) from the pull-off force (JKR, seed 4.2.1)."""
        return float(adhesion_from_pull_off(self.pull_off_force(spring_constant)))


@dataclass(frozen=True, eq=False)
class FrictionLoop:
    """Per load: mean S_n (V) and the S_l lines (V, ``(m, n)``) of trace (uphill) and retrace."""

    tilt_deg: float
    s_n: np.ndarray
    sl_trace: np.ndarray
    sl_retrace: np.ndarray

    def slopes(self, crosstalk: float) -> tuple[float, float]:
        """``(dS̄_l/dS_n retrace, trace)``: the eq. 3.26 and 3.27 slopes after removing α."""
        up = np.polyfit(self.s_n, self.sl_trace.mean(axis=1), 1)[0] - crosstalk
        down = np.polyfit(self.s_n, self.sl_retrace.mean(axis=1), 1)[0] - crosstalk
        return float(down), float(up)

    def calibrate(self, crosstalk: float, spring_constant: float, normal_gain: float) -> LateralCalibration:
        """(k_l K_l / h, μ) from eq. 3.26-3.27, solved numerically."""
        down, up = self.slopes(crosstalk)
        return calibrate_lateral_gain(down, up, self.tilt_deg, spring_constant, normal_gain)


def force_curve_signals(model: SignalModel, params: WorldParams, x: float, z_top: float,
                        depth: float, n: int, rng: np.random.Generator) -> ForceCurve:
    """A force curve from ``z_top`` down to ``-depth`` and back, ``n`` samples each way."""
    k = model.lever.spring_constant
    pull = params.adhesion.pull_off_fraction * params.adhesion.tip_substrate
    z_app = np.linspace(z_top, -depth, n)
    z_ret = z_app[::-1].copy()
    defl_app = np.maximum(-z_app, 0.0)
    held = np.cumprod(k * z_ret < pull).astype(bool)     # adhered until the pull first exceeds it
    defl_ret = np.where(held, -z_ret, 0.0)
    out = []
    for z, defl in ((z_app, defl_app), (z_ret, defl_ret)):
        sn_bar, sl_bar = model.bar_signals(np.zeros((n, 2)), defl)
        out += list(model.raw(sn_bar, sl_bar, np.full(n, x), z + defl, rng))
    return ForceCurve(z_app, out[0], out[1], z_ret, out[2], out[3])


def slope_friction(f_n, tan_slope, mu: float, shear: float) -> np.ndarray:
    """Lateral force against the tip's motion (nN) sliding under the load ``f_n`` (nN) on a
    hard surface whose slope along the motion is ``tan_slope`` (> 0 uphill), with the
    friction μN + ``shear`` (seed eq. 3.14-3.19): uphill N' = (F_n + A sin θ)/(cos θ − μ sin θ)
    and N' sin θ + (μN' + A) cos θ against the motion; downhill N = (F_n − A sin θ)/(cos θ +
    μ sin θ) and (μN + A) cos θ − N sin θ. Flat (θ = 0): μ F_n + A either way."""
    f_n, t = np.broadcast_arrays(np.asarray(f_n, float), np.asarray(tan_slope, float))
    th = np.arctan(np.abs(t))
    s, c = np.sin(th), np.cos(th)
    n_up = (f_n + shear * s) / (c - mu * s)
    n_down = (f_n - shear * s) / (c + mu * s)
    return np.where(t >= 0, n_up * s + (mu * n_up + shear) * c, (mu * n_down + shear) * c - n_down * s)


def friction_loop_signals(model: SignalModel, params: WorldParams, x: float, tilt_deg: float,
                          loads: np.ndarray, width: float, n: int, rng: np.random.Generator) -> FrictionLoop:
    """Trace and retrace lines of ``n`` samples over ``width`` nm at each load (nN)."""
    mu = params.friction.mu_ts
    shear = params.friction.nu * params.adhesion.tip_substrate
    f_n = np.asarray(loads, float)
    tan = math.tan(math.radians(tilt_deg))
    lat_up = slope_friction(f_n, tan, mu, shear)
    lat_down = -slope_friction(f_n, -tan, mu, shear)
    lever = model.lever
    sn_bar = np.clip(f_n / (lever.spring_constant * lever.normal_gain), -lever.full_scale, lever.full_scale)
    xs = x + np.linspace(0.0, width, n)
    lines = []
    for lat, xline in ((lat_up, xs), (lat_down, xs[::-1])):
        sl_bar = np.clip(lat / lever.lateral_gain, -lever.full_scale, lever.full_scale)
        sn_grid = np.repeat(sn_bar[:, None], n, axis=1)
        sl_grid = np.repeat(sl_bar[:, None], n, axis=1)
        xg = np.broadcast_to(xline, sn_grid.shape)
        s_n, s_l = model.raw(sn_grid, sl_grid, xg, np.zeros(sn_grid.shape), rng)
        lines.append((s_n, s_l))
    s_n_mean = np.concatenate([lines[0][0], lines[1][0]], axis=1).mean(axis=1)
    return FrictionLoop(float(tilt_deg), s_n_mean, lines[0][1], lines[1][1])
