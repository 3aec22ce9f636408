"""The analysis of ``nanoasm calibrate``'s measurements (seed 3.4-3.6), each value with its
standard uncertainty (1σ, from the scatter of the fits, propagated to first order).

- :func:`force_curve_fit`: K_n from the contact slope of S_n against the piezo's z on a
  hard surface (eq. 3.13), α from S_l against S_n while pressing (§3.5), and the change
  of the free-air baselines from the lift height to contact (the approach above contact);
- :func:`flat_loop_fit`: the half-width W of a friction loop on the substrate against
  S_n: ``dW/dS_n = μ_ts k K_n / (k_l K_l / h)``;
- :func:`slope_fit`: (k_l K_l / h, μ) from the loops on a tilted surface (eq. 3.26-3.27 with
  DESIGN.md's pairing: the smaller, downhill slope in 3.26);
- :func:`edge_fit`: C2 from where the tip climbs a step at several loads: the tip sits
  ``C2 S̄n`` along the lever axis from the piezo (eq. 3.30-3.34), so the piezo meets the
  edge ``C2 ΔS̄n`` earlier or later.

Signals in V, lengths in nm, forces in nN.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from scipy.stats import linregress

from nanoasm.errors import NanoasmError
from nanoasm.world.cantilever import calibrate_lateral_gain


class Value(NamedTuple):
    """A measured value and its standard uncertainty."""

    value: float
    sigma: float


class CalibrationFailed(NanoasmError):
    """A measurement that cannot give its constant (too few points, no contact, no edge);
    ``str(err)`` is one line naming the step."""


def line_fit(x, y, what: str) -> tuple[Value, float]:
    """Least-squares slope (with its standard error) and intercept of ``y`` on ``x``."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if x.size < 3 or np.ptp(x) == 0:
        raise CalibrationFailed(f"{what}: too few distinct points to fit a line ({x.size})")
    r = linregress(x, y)
    return Value(float(r.slope), float(r.stderr)), float(r.intercept)


class ForceCurveFit(NamedTuple):
    normal_gain: Value        # K_n, nm/V
    crosstalk: Value          # α
    contact_z: float          # z (nm) where the contact line meets the free-air baseline
    shift_n: float            # A at contact less A at the lift height, V
    shift_l: float            # B likewise, V


def force_curve_fit(z, s_n, s_l, lift: float, full_scale: float) -> ForceCurveFit:
    """K_n, α and the baselines' change with height from an approach (z falling, nm)."""
    z, s_n, s_l = (np.asarray(v, float) for v in (z, s_n, s_l))
    free = z > 30.0
    if np.count_nonzero(free) < 10:
        raise CalibrationFailed("force curve: too few samples above the surface")
    deg = 2 if np.ptp(z[free]) > 100.0 else 1
    a_fit, b_fit = np.polyfit(z[free], s_n[free], deg), np.polyfit(z[free], s_l[free], deg)
    noise = float(np.std(s_n[free] - np.polyval(a_fit, z[free])))
    pressed = s_n - np.polyval(a_fit, z) > max(0.1, 10.0 * noise)
    if not pressed.any():
        raise CalibrationFailed("force curve: the signal never rose: no contact within the ramp")
    z_touch = float(z[np.argmax(pressed)])
    contact = (z < z_touch - 10.0) & (np.abs(s_n) < 0.95 * full_scale) & (np.abs(s_l) < 0.95 * full_scale)
    slope_n, icpt = line_fit(z[contact], s_n[contact], "force curve")
    slope_l, _ = line_fit(z[contact], s_l[contact], "force curve (lateral)")
    if not slope_n.value < 0:
        raise CalibrationFailed("force curve: S_n does not rise as the piezo presses")
    k_n = -1.0 / slope_n.value
    alpha = slope_l.value / slope_n.value
    alpha_sigma = math.hypot(slope_l.sigma / slope_n.value, alpha * slope_n.sigma / slope_n.value)
    # where the contact line meets the free-air baseline: the surface
    zs = np.linspace(z_touch - 50.0, z_touch + 50.0, 201)
    z0 = float(zs[np.argmin(np.abs(icpt + slope_n.value * zs - np.polyval(a_fit, zs)))])
    return ForceCurveFit(Value(k_n, slope_n.sigma * k_n * k_n), Value(alpha, alpha_sigma), z0,
                         float(np.polyval(a_fit, z0) - np.polyval(a_fit, lift)),
                         float(np.polyval(b_fit, z0) - np.polyval(b_fit, lift)))


def flat_loop_fit(s_n, half_width) -> Value:
    """``dW/dS_n`` of a substrate friction loop: the half-width W (V) at each load's mean S_n."""
    slope, _ = line_fit(s_n, half_width, "friction loop on the substrate")
    return slope


def _propagate(fn, values: list[Value]) -> tuple[np.ndarray, np.ndarray]:
    """``fn`` at the values and the first-order standard uncertainty of each output."""
    x0 = np.array([v.value for v in values])
    f0 = np.asarray(fn(*x0), float)
    var = np.zeros_like(f0)
    for i, v in enumerate(values):
        if v.sigma <= 0:
            continue
        h = v.sigma * 1e-3
        x = x0.copy()
        x[i] += h
        var += ((np.asarray(fn(*x), float) - f0) / h * v.sigma) ** 2
    return f0, np.sqrt(var)


class SlopeFit(NamedTuple):
    lateral_gain: Value        # k_l K_l / h, nN/V
    mu: Value                  # friction coefficient on the tilted surface
    tilt: Value                # θ, degrees
    slopes: tuple[Value, Value]  # dS_l/dS_n downhill (eq. 3.26), uphill (eq. 3.27), α removed


def slope_fit(tilt: Value, down: Value, up: Value, spring_constant: float, normal_gain: Value) -> SlopeFit:
    """Solve eq. 3.26-3.27 for (k_l K_l / h, μ); uncertainties from the slopes, θ and K_n."""
    def solve(th, s_minus, s_plus, k_n):
        cal = calibrate_lateral_gain(s_minus, s_plus, th, spring_constant, k_n)
        return cal.lateral_gain, cal.mu

    try:
        f, s = _propagate(solve, [tilt, down, up, normal_gain])
    except ValueError as e:
        raise CalibrationFailed(f"friction loops on the slope: {e}") from None
    return SlopeFit(Value(float(f[0]), float(s[0])), Value(float(f[1]), float(s[1])), tilt, (down, up))


def friction_from_substrate(dw_dsn: Value, lateral_gain: Value, spring_constant: float,
                            normal_gain: Value) -> Value:
    """μ_ts = (k_l K_l / h) / (k K_n) · dW/dS_n (the substrate loop's half-width per volt)."""
    f, s = _propagate(lambda d, g, k_n: g / (spring_constant * k_n) * d, [dw_dsn, lateral_gain, normal_gain])
    return Value(float(f), float(s))


def climb_index(s_n, rise: float = 0.15, hold: int = 3) -> int | None:
    """First sample where S_n stays ``rise`` V above its level at the start (the tip on a step)."""
    s_n = np.asarray(s_n, float)
    if s_n.size < 20:
        return None
    start = s_n[: max(10, s_n.size // 5)]
    level = float(np.median(start))
    noise = 1.4826 * float(np.median(np.abs(start - level)))
    up = (s_n > level + max(rise, 10.0 * noise)).astype(int)
    run = np.convolve(up, np.ones(hold, int), mode="valid")
    hits = np.flatnonzero(run == hold)
    return int(hits[0]) if hits.size else None


def edge_fit(s_n_before, position, t) -> Value:
    """C2 (nm/V) from the piezo's position along the lever axis where the tip climbed the
    step (nm) at each pass's S_n before the step (V) and time (s): ``position = e + v t −
    C2 S̄n``, the step drifting steadily at ``v`` (least squares over the three)."""
    s_n, pos, t = (np.asarray(v, float) for v in (s_n_before, position, t))
    if s_n.size < 5 or np.ptp(s_n) == 0:
        raise CalibrationFailed(f"edge: too few passes at distinct loads to fit C2 ({s_n.size})")
    design = np.column_stack([np.ones_like(s_n), t - t.mean(), s_n])
    coef, *_ = np.linalg.lstsq(design, pos, rcond=None)
    dof = s_n.size - 3
    resid = pos - design @ coef
    cov = np.linalg.pinv(design.T @ design) * (resid @ resid / dof if dof > 0 else 0.0)
    c2 = float(-coef[2])
    if not c2 > 0:      # a drift that is not steady (a jump between passes) spoils the fit
        raise CalibrationFailed(f"edge: C2 came out {c2:.3g} nm/V, not positive (the step moved unsteadily "
                                f"between passes?)")
    return Value(c2, float(math.sqrt(max(cov[2, 2], 0.0))))


__all__ = ["CalibrationFailed", "ForceCurveFit", "SlopeFit", "Value", "climb_index", "edge_fit",
           "flat_loop_fit", "force_curve_fit", "friction_from_substrate", "line_fit", "slope_fit"]
