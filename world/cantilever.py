"""Cantilever forces, signals, calibration and tip position error (seed chapter 3).

Units: nm, nN, V, degrees. The spring constant k in N/m is numerically nN/nm, so
F = k·K_n·S_n comes out in nN with K_n in nm/V and S_n in V: no SI conversion is needed
anywhere in this module. Frames: the AFM (scanner) frame and the cantilever frame,
related by R(ψ) of eq. 3.7 (ψ the scan angle); vectors are ``(..., 2)`` or ``(..., 3)``
arrays with the components on the last axis. Baseline images are in image order
``img[j, i]`` (row j from the top, +y; column i along x): eq. 3.29's A(i, j) is A[j, i].
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import NamedTuple

import numpy as np
from scipy.optimize import brentq


@dataclass(frozen=True)
class Cantilever:
    """Cantilever and detector constants; defaults are the seed's 0.12 N/m V-shaped lever.

    ``c1_override`` None uses C1 = K_n h / l (§3.6.3; 1.335 nm/V, the seed rounds to 1.3).
    ``lateral_gain`` is k_l K_l / h from eq. 3.26–3.27 with the errata pairing (38.27 nN/V;
    the seed's graphical value is 37.8). ``full_scale`` is the ±10 V signal range (§3.6.4).
    """

    spring_constant: float = 0.12      # k, N/m (= nN/nm), §3.4.2
    normal_gain: float = 89.0          # K_n, nm/V, eq. 3.13
    lateral_gain: float = 38.27        # k_l K_l / h, nN/V, eq. 3.26–3.27
    tip_height: float = 3000.0         # h, nm (includes the lever thickness), Fig. 3.7
    lever_length: float = 200_000.0    # l, nm
    c2: float = 23.0                   # nm/V, §3.6.4
    c1_override: float | None = None   # nm/V, §3.6.3
    crosstalk: float = 0.18            # α, normal-to-lateral, §3.5 (Fig. 3.17)
    full_scale: float = 10.0           # V

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "c1_override" and v is None:
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"{f.name} must be a finite number, got {v!r}")
            if f.name != "crosstalk" and v <= 0:
                raise ValueError(f"{f.name} must be positive, got {v!r}")

    @property
    def c1(self) -> float:
        """C1 in nm/V: lateral tip shift per lateral volt (§3.6.3, C1 = K_n h / l)."""
        if self.c1_override is not None:
            return self.c1_override
        return self.normal_gain * self.tip_height / self.lever_length

    @property
    def twist_gain(self) -> float:
        """K_l ≈ K_n / l in rad/V (eq. 3.3 with §3.6.3)."""
        return self.normal_gain / self.lever_length


#: The seed's lever (0.12 N/m, §3.4–3.6), the default of every function below.
SEED_LEVER = Cantilever()


# --- frames ----------------------------------------------------------------------------

def scan_rotation(psi_deg: float) -> np.ndarray:
    """R(ψ) of eq. 3.7: v_cantilever = R v_AFM. R is orthogonal, so R⁻¹ = Rᵀ."""
    c, s = math.cos(math.radians(psi_deg)), math.sin(math.radians(psi_deg))
    return np.array([[-c, s, 0.0], [-s, -c, 0.0], [0.0, 0.0, 1.0]])


def _frame(v, rot: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    n = v.shape[-1] if v.ndim else 0
    if n not in (2, 3):
        raise ValueError(f"vectors need 2 or 3 components on the last axis, got shape {v.shape}")
    return v @ rot[:n, :n].T


def to_cantilever(v_afm, psi_deg: float) -> np.ndarray:
    """AFM-frame vectors to the cantilever frame: R v (eq. 3.7)."""
    return _frame(v_afm, scan_rotation(psi_deg))


def to_afm(v_cantilever, psi_deg: float) -> np.ndarray:
    """Cantilever-frame vectors to the AFM frame: R⁻¹ v (eq. 3.12)."""
    return _frame(v_cantilever, scan_rotation(psi_deg).T)


def motion_angle_deg(v_afm, psi_deg: float) -> np.ndarray:
    """φ: angle of the tip's lateral motion from the cantilever X axis (before eq. 3.8).

    0 for a zero motion, the singular direction, where :func:`force_from_signals` reports
    no F_x.
    """
    vc = to_cantilever(np.asarray(v_afm, dtype=float)[..., :2], psi_deg)
    return np.degrees(np.arctan2(vc[..., 1], vc[..., 0]))


# --- signals and forces ----------------------------------------------------------------

def photodiode_signals(a, b, c, d, full_scale: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """(S_n, S_l) in V from the quadrant outputs (after eq. 3.4), ratio ±1 ↦ ±full_scale."""
    a, b, c, d = (np.asarray(q, dtype=float) for q in (a, b, c, d))
    total = a + b + c + d
    if not np.all(np.isfinite(total)) or np.any(total <= 0):
        raise ValueError("photodiode sum a + b + c + d must be positive and finite (laser on the detector)")
    return full_scale * ((a + b) - (c + d)) / total, full_scale * ((a + c) - (b + d)) / total


def signals_from_force(force_c, lever: Cantilever = SEED_LEVER) -> tuple[np.ndarray, np.ndarray]:
    """(S_n, S_l) in V for tip forces (F_x, F_y, F_z) in nN in the cantilever frame.

    Forward form of eq. 3.5, 3.6 and 3.9: S_n = (F_z + (h/l) F_x)/(k K_n),
    S_l = F_y / (k_l K_l / h); both saturate at ±full_scale.
    """
    f = np.asarray(force_c, dtype=float)
    fn = f[..., 2] + lever.tip_height / lever.lever_length * f[..., 0]
    s_n = fn / (lever.spring_constant * lever.normal_gain)
    s_l = f[..., 1] / lever.lateral_gain
    return np.clip(s_n, -lever.full_scale, lever.full_scale), np.clip(s_l, -lever.full_scale, lever.full_scale)


def force_from_signals(s_n, s_l, phi_deg, lever: Cantilever = SEED_LEVER,
                       phi_floor_deg: float = 5.0) -> np.ndarray:
    """Tip force (F_x, F_y, F_z) in nN, cantilever frame, from compensated signals (eq. 3.11).

    F_y = (k_l K_l/h) S_l; F_x = F_y cot φ (the lateral force opposes the motion at angle
    φ from X, eq. 3.8; the seed's "tan φ" in 3.10–3.11 would not be singular at φ = 0);
    F_z = k K_n S_n − (h/l) F_x. At φ → 0 F_x is unmeasurable: within ``phi_floor_deg``
    of the X axis cot φ is replaced by cos φ sin φ / sin²(floor), continuous, exact
    outside the floor, 0 at φ = 0, so |F_x| ≤ |F_y| / sin(floor) for every φ.
    """
    if not 0.0 < phi_floor_deg < 90.0:
        raise ValueError(f"phi_floor_deg must lie in (0, 90), got {phi_floor_deg!r}")
    phi = np.radians(np.asarray(phi_deg, dtype=float))
    sin_p, cos_p = np.sin(phi), np.cos(phi)
    eps2 = math.sin(math.radians(phi_floor_deg)) ** 2
    f_y = lever.lateral_gain * np.asarray(s_l, dtype=float)
    f_x = f_y * cos_p * sin_p / np.maximum(sin_p * sin_p, eps2)
    f_z = lever.spring_constant * lever.normal_gain * np.asarray(s_n, dtype=float) \
        - lever.tip_height / lever.lever_length * f_x
    return np.stack(np.broadcast_arrays(f_x, f_y, f_z), axis=-1)


def tip_force_afm(s_n, s_l, v_afm, psi_deg: float, lever: Cantilever = SEED_LEVER,
                  phi_floor_deg: float = 5.0) -> np.ndarray:
    """Tip force (F_px, F_py, F_pz) in nN in the AFM frame for a tip moving along ``v_afm``
    (eq. 3.11–3.12)."""
    phi = motion_angle_deg(v_afm, psi_deg)
    return to_afm(force_from_signals(s_n, s_l, phi, lever, phi_floor_deg), psi_deg)


def twist_angle_deg(s_l, lever: Cantilever = SEED_LEVER) -> np.ndarray:
    """Cantilever twist θx = K_l S_l in degrees, K_l ≈ K_n/l (eq. 3.3, §3.6.3)."""
    return np.degrees(lever.twist_gain * np.asarray(s_l, dtype=float))


# --- signal compensation ---------------------------------------------------------------

def baseline_index(x, y, scan_range: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices (i, j) into an n × n baseline for a tip at (x, y) nm from the scan centre.

    Eq. 3.29 with int(·) rounding half up, clipped to the matrix: i = round((n−1)(x/L + 1/2)),
    j = n − 1 − round((n−1)(y/L + 1/2)). For odd n this is the seed's form exactly; for
    even n the seed's int(n/2) offset would step past the last index.
    """
    if not (scan_range > 0 and math.isfinite(scan_range)):
        raise ValueError(f"scan_range must be positive, got {scan_range!r}")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n must be a positive integer, got {n!r}")
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    i = np.clip(np.floor((n - 1) * (x / scan_range + 0.5) + 0.5), 0, n - 1)
    j = n - 1 - np.clip(np.floor((n - 1) * (y / scan_range + 0.5) + 0.5), 0, n - 1)
    return i.astype(int), j.astype(int)


def _baseline_at(baseline, x, y, scan_range: float, name: str) -> np.ndarray:
    base = np.asarray(baseline, dtype=float)
    if base.ndim == 0:
        return base
    if base.ndim != 2 or base.shape[0] != base.shape[1]:
        raise ValueError(f"{name} must be a scalar or a square (n, n) image, got shape {base.shape}")
    i, j = baseline_index(x, y, scan_range, base.shape[0])
    return base[j, i]


def compensate_signals(s_n, s_l, x, y, baseline_n, baseline_l, scan_range: float,
                       crosstalk: float) -> tuple[np.ndarray, np.ndarray]:
    """(S̄_n, S̄_l) in V: S̄_n = S_n − A(i,j), S̄_l = S_l − B(i,j) − α(S_n − A(i,j)) (eq. 3.28)."""
    a = _baseline_at(baseline_n, x, y, scan_range, "baseline_n")
    b = _baseline_at(baseline_l, x, y, scan_range, "baseline_l")
    sn_bar = np.asarray(s_n, dtype=float) - a
    return sn_bar, np.asarray(s_l, dtype=float) - b - crosstalk * sn_bar


def raw_signals(sn_bar, sl_bar, x, y, baseline_n, baseline_l, scan_range: float,
                crosstalk: float) -> tuple[np.ndarray, np.ndarray]:
    """Detector signals (S_n, S_l) in V that compensate to (S̄_n, S̄_l): eq. 3.28 inverted."""
    a = _baseline_at(baseline_n, x, y, scan_range, "baseline_n")
    b = _baseline_at(baseline_l, x, y, scan_range, "baseline_l")
    sn_bar = np.asarray(sn_bar, dtype=float)
    return sn_bar + a, np.asarray(sl_bar, dtype=float) + b + crosstalk * sn_bar


# --- calibration -----------------------------------------------------------------------

def _slope(xs, ys, name: str) -> float:
    xs, ys = np.asarray(xs, dtype=float).ravel(), np.asarray(ys, dtype=float).ravel()
    if xs.shape != ys.shape or xs.size < 2:
        raise ValueError(f"{name}: need two equal-length arrays of at least 2 samples")
    if not (np.all(np.isfinite(xs)) and np.all(np.isfinite(ys))):
        raise ValueError(f"{name}: samples must be finite")
    if np.ptp(xs) == 0:
        raise ValueError(f"{name}: the signal does not vary, no slope")
    return float(np.polyfit(xs, ys, 1)[0])


def normal_gain_from_force_curve(z_nm, s_n) -> float:
    """K_n = dδz/dS_n in nm/V from the contact part of a force curve on a hard surface (eq. 3.13).

    On a hard surface the deflection follows the piezo, so K_n is the magnitude of the
    least-squares slope of piezo z (nm) against S_n (V).
    """
    return abs(_slope(s_n, z_nm, "normal_gain_from_force_curve"))


def crosstalk_from_force_curve(s_n, s_l) -> float:
    """α: least-squares slope of S_l against S_n while pressing without lateral motion (§3.5)."""
    return _slope(s_n, s_l, "crosstalk_from_force_curve")


class LateralCalibration(NamedTuple):
    lateral_gain: float  # k_l K_l / h, nN/V
    mu: float            # tip–surface friction coefficient


def calibrate_lateral_gain(slope_minus: float, slope_plus: float, tilt_deg: float,
                           spring_constant: float = 0.12, normal_gain: float = 89.0) -> LateralCalibration:
    """Solve eq. 3.26–3.27 numerically for (k_l K_l / h, μ) from a tilted-surface friction loop.

    ``slope_minus`` is dS_l/dS_n of the branch of eq. 3.26, where friction opposes the
    slope's lateral term (the smaller slope); ``slope_plus`` of eq. 3.27. With G =
    (k_l K_l/h)/(k K_n) and λ = atan μ the equations read G·slope_minus = tan(θ − λ),
    G·slope_plus = tan(θ + λ); eliminating G leaves one equation in λ, monotone on
    [0, min(θ, 90° − θ)], solved with Brent's method.
    """
    for name, v in (("slope_minus", slope_minus), ("slope_plus", slope_plus),
                    ("spring_constant", spring_constant), ("normal_gain", normal_gain)):
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be positive, got {v!r}")
    if not 0.0 < tilt_deg < 90.0:
        raise ValueError(f"tilt_deg must lie in (0, 90), got {tilt_deg!r}")
    if not slope_plus > slope_minus:
        raise ValueError(f"slope_plus ({slope_plus!r}) must exceed slope_minus ({slope_minus!r}); "
                         "paired the other way eq. 3.26-3.27 give mu < 0")
    th = math.radians(tilt_deg)

    def residual(lam: float) -> float:
        return slope_plus * math.tan(th - lam) - slope_minus * math.tan(th + lam)

    lam = brentq(residual, 0.0, min(th, 0.5 * math.pi - th), xtol=1e-15, rtol=1e-15)
    g = math.tan(th + lam) / slope_plus
    return LateralCalibration(g * spring_constant * normal_gain, math.tan(lam))


# --- tip position error ----------------------------------------------------------------

def tip_deflection(sn_bar, sl_bar, lever: Cantilever = SEED_LEVER) -> np.ndarray:
    """Tip displacement (δx, δy, δz) in nm, cantilever frame: (C2 S̄_n, C1 S̄_l, K_n S̄_n) (eq. 3.30–3.34)."""
    sn, sl = np.broadcast_arrays(np.asarray(sn_bar, dtype=float), np.asarray(sl_bar, dtype=float))
    return np.stack((lever.c2 * sn, lever.c1 * sl, lever.normal_gain * sn), axis=-1)


def tip_offset(sn_bar, sl_bar, psi_deg: float, lever: Cantilever = SEED_LEVER) -> np.ndarray:
    """Tip displacement R⁻¹δ in nm in the AFM frame: tip = piezo + R⁻¹δ (§3.6.2)."""
    return to_afm(tip_deflection(sn_bar, sl_bar, lever), psi_deg)


def compensated_command(target_xy, sn_bar, sl_bar, psi_deg: float,
                        lever: Cantilever = SEED_LEVER) -> np.ndarray:
    """Piezo (x, y) in nm that puts the deflected tip on ``target_xy``: target − (R⁻¹δ)_xy (§3.6.2)."""
    return np.asarray(target_xy, dtype=float) - tip_offset(sn_bar, sl_bar, psi_deg, lever)[..., :2]
