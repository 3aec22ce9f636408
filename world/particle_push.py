"""Tip–object–substrate equilibrium for a push (seed eq. 4.1–4.7, 4.19–4.20).

The object slides on the substrate (no rolling, no tip–object friction, seed §4.2.1);
the tip meets it at the angle θ = θx + γ (cantilever twist plus the tip's half opening
angle). Forces are in nN, angles in degrees, lengths in nm. Every function takes a
factor ``rho`` (ρ of eq. 4.13): 1 for a particle (eq. 4.6–4.7) and ρ(l) of
:func:`nanoasm.world.pivot.rho` for a rod pushed at l (eq. 4.19–4.20), which have the
same form with μos replaced by ρμos in the denominator. Inputs may be floats or arrays.

Adhesions scale with the nominal contact areas (seed §4.2.1): F^a_ot / F^a_ts =
A_ot / A_ts and F^a_os / F^a_ts = A_os / A_ts, with F^a_ts from the pull-off force of a
force curve (JKR: pull-off = 75 % of the adhesion). The contact areas here are JKR
zero-load contacts (sphere: a³ = 9πwR²/(2E*); cylinder: b³ = 32wR²/(πE*)); the seed
names the JKR ratio but no contact radius, so that choice is ours. With w in nN/nm
(= J/m²) and E* in GPa (= nN/nm²) no unit conversion is needed.
"""

from __future__ import annotations

import math
from enum import Enum

import numpy as np

#: JKR pull-off force as a fraction of the adhesive force (seed §4.2.1, ref. [62]).
JKR_PULL_OFF_FRACTION = 0.75


class PushOutcome(str, Enum):
    """What a push with a given normal force does (seed §4.2.1, after eq. 4.7)."""

    MOVES = "moves"            # F_z ≥ F̄z and θ < θmax: the tip stays down, the object slides
    SLIPS_OVER = "slips_over"  # F_z < F̄z: the tip lifts and slips over the object
    JAMMED = "jammed"          # θ ≥ θmax: the tip squeezes the object into the substrate


def _check(name: str, value, *, lo: float | None = None, lo_open: bool = False) -> np.ndarray:
    if isinstance(value, float):    # one number (the simulator's every step): no array tests
        if math.isfinite(value) and (lo is None or (value > lo if lo_open else value >= lo)):
            return np.asarray(value)
    arr = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {value!r}")
    if lo is not None and (np.any(arr <= lo) if lo_open else np.any(arr < lo)):
        raise ValueError(f"{name} must be {'>' if lo_open else '>='} {lo:g}, got {value!r}")
    return arr


def _theta(theta_deg) -> np.ndarray:
    th = _check("theta_deg", theta_deg)
    if np.any(np.abs(th) >= 90.0):
        raise ValueError(f"theta_deg must lie in (-90, 90), got {theta_deg!r}")
    return np.radians(th)


def push_angle_deg(twist_deg, half_angle_deg):
    """θ = θx + γ in degrees: cantilever twist plus tip half opening angle (eq. 4.1)."""
    return _check("twist_deg", twist_deg) + _check("half_angle_deg", half_angle_deg, lo=0.0)


def theta_max_deg(mu_os, rho=1.0):
    """θmax = atan(1/(ρ μos)) in degrees (after eq. 4.6; rods after eq. 4.19); 90° if μos = 0."""
    m = _check("mu_os", mu_os, lo=0.0) * _check("rho", rho, lo=0.0, lo_open=True)
    return np.degrees(np.arctan2(1.0, m))


def _jam_denominator(th: np.ndarray, m: np.ndarray) -> np.ndarray:
    """cos θ − m sin θ written as √(1 + m²)·sin(θmax − θ): exact near θ → θmax."""
    return np.hypot(1.0, m) * np.sin(np.arctan2(1.0, m) - th)


def _transmitted(theta_deg, mu_os, nu, f_os_a, rho):
    """ρ(μos + ν) F^a_os / (cos θ − ρ μos sin θ), +inf at or beyond θmax (eq. 4.6, 4.19)."""
    th = _theta(theta_deg)
    mu = _check("mu_os", mu_os, lo=0.0)
    r = _check("rho", rho, lo=0.0, lo_open=True)
    num = r * (mu + _check("nu", nu, lo=0.0)) * _check("f_os_a", f_os_a, lo=0.0)
    den = _jam_denominator(th, r * mu)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(den > 0.0, num / np.where(den > 0.0, den, 1.0), np.inf)
    return th, out


def tip_object_repulsion(theta_deg, mu_os, nu, f_os_a, f_ot_a, rho=1.0):
    """Repulsive tip–object force F^r_ot in nN (eq. 4.6; rods eq. 4.19); +inf if θ ≥ θmax."""
    _, t = _transmitted(theta_deg, mu_os, nu, f_os_a, rho)
    return _check("f_ot_a", f_ot_a, lo=0.0) + t


def min_normal_force(theta_deg, mu_os, nu, f_os_a, f_ts_a, rho=1.0):
    """Minimum normal force F̄z in nN that keeps the tip on the substrate (eq. 4.7, 4.20).

    F̄z = ρ(μos + ν) sin θ / (cos θ − ρ μos sin θ) · F^a_os − F^a_ts; negative when the
    tip–substrate adhesion alone holds the tip down; +inf when θ ≥ θmax.
    """
    th, t = _transmitted(theta_deg, mu_os, nu, f_os_a, rho)
    return t * np.sin(th) - _check("f_ts_a", f_ts_a, lo=0.0)   # θ ≥ θmax > 0 keeps +inf


def push_lateral_force(theta_deg, mu_os, nu, f_os_a, f_ts_a, f_z, mu_ts=0.0, rho=1.0):
    """Lateral force F_l in nN the cantilever carries during a push (eq. 4.4).

    F_l = (F^r_to − F^a_to) cos θ + F^f_ts with F^f_ts = μts (F_z − F̄z), the tip–substrate
    friction on the excess load (eq. 4.4 with 4.6 and 4.7; μts is our parameter, the seed
    leaves F^f_ts unspecified). +inf if θ ≥ θmax.
    """
    contact, friction = push_force_parts(theta_deg, mu_os, nu, f_os_a, f_ts_a, f_z, mu_ts, rho)
    return contact + friction


def push_force_parts(theta_deg, mu_os, nu, f_os_a, f_ts_a, f_z, mu_ts=0.0, rho=1.0):
    """The two parts of :func:`push_lateral_force` (nN): the object's ``(F^r_to − F^a_to)
    cos θ``, along the tip–object contact normal, and the tip–substrate friction
    ``μts (F_z − F̄z)``, against the tip's motion."""
    th, t = _transmitted(theta_deg, mu_os, nu, f_os_a, rho)
    excess = np.maximum(_check("f_z", f_z) - min_normal_force(theta_deg, mu_os, nu, f_os_a, f_ts_a, rho), 0.0)
    return t * np.cos(th), _check("mu_ts", mu_ts, lo=0.0) * excess


def push_outcome(f_z: float, theta_deg: float, mu_os: float, nu: float, f_os_a: float,
                 f_ts_a: float, rho: float = 1.0) -> PushOutcome:
    """Whether a push with normal force ``f_z`` (nN) moves the object (eq. 4.6–4.7, 4.19–4.20)."""
    fz = float(_check("f_z", f_z))
    bar = float(min_normal_force(theta_deg, mu_os, nu, f_os_a, f_ts_a, rho))
    if math.isinf(bar) or float(theta_deg) >= float(theta_max_deg(mu_os, rho)):
        return PushOutcome.JAMMED
    return PushOutcome.MOVES if fz >= bar else PushOutcome.SLIPS_OVER


def push_succeeds(f_z: float, theta_deg: float, mu_os: float, nu: float, f_os_a: float,
                  f_ts_a: float, rho: float = 1.0) -> bool:
    """True if the push moves the object, False if the tip slips over or jams (eq. 4.7)."""
    return push_outcome(f_z, theta_deg, mu_os, nu, f_os_a, f_ts_a, rho) is PushOutcome.MOVES


# --- adhesion from contact areas -------------------------------------------------------

def adhesion_from_pull_off(pull_off_nn):
    """Tip–substrate adhesion F^a_ts in nN from the force-curve pull-off (§4.2.1: JKR 75 %)."""
    return _check("pull_off_nn", pull_off_nn, lo=0.0) / JKR_PULL_OFF_FRACTION


def effective_radius(r1_nm, r2_nm=math.inf):
    """R1 R2 / (R1 + R2) in nm; ``r2_nm`` = inf (default) for a flat."""
    r1 = _check("r1_nm", r1_nm, lo=0.0, lo_open=True)
    r2 = np.asarray(r2_nm, dtype=float)
    if np.any(np.isnan(r2)) or np.any(r2 <= 0.0):
        raise ValueError(f"r2_nm must be > 0 (inf for a flat), got {r2_nm!r}")
    return np.where(np.isinf(r2), r1, r1 * r2 / (r1 + np.where(np.isinf(r2), 0.0, r2)))


def jkr_contact_radius(radius_nm, work_of_adhesion, modulus_gpa):
    """JKR zero-load contact radius in nm of a sphere on a flat: a³ = 9πwR²/(2E*).

    ``work_of_adhesion`` w in nN/nm (J/m²), ``modulus_gpa`` the reduced modulus E*.
    """
    r = _check("radius_nm", radius_nm, lo=0.0, lo_open=True)
    w = _check("work_of_adhesion", work_of_adhesion, lo=0.0, lo_open=True)
    e = _check("modulus_gpa", modulus_gpa, lo=0.0, lo_open=True)
    return np.cbrt(9.0 * math.pi * w * r**2 / (2.0 * e))


def jkr_contact_halfwidth(radius_nm, work_of_adhesion, modulus_gpa):
    """JKR zero-load contact half-width in nm of a cylinder on a flat: b³ = 32wR²/(πE*)."""
    r = _check("radius_nm", radius_nm, lo=0.0, lo_open=True)
    w = _check("work_of_adhesion", work_of_adhesion, lo=0.0, lo_open=True)
    e = _check("modulus_gpa", modulus_gpa, lo=0.0, lo_open=True)
    return np.cbrt(32.0 * w * r**2 / (math.pi * e))


def adhesion_from_area(f_ts_a, area_nm2, area_ts_nm2):
    """F^a = F^a_ts · A / A_ts in nN: adhesion scales with the contact area (§4.2.1)."""
    return (_check("f_ts_a", f_ts_a, lo=0.0) * _check("area_nm2", area_nm2, lo=0.0)
            / _check("area_ts_nm2", area_ts_nm2, lo=0.0, lo_open=True))


def particle_adhesions(f_ts_a, tip_radius_nm, particle_radius_nm):
    """(F^a_ot, F^a_os) in nN for a spherical particle, scaled from F^a_ts by JKR areas.

    With the same w and E* at every contact, A = πa² ∝ R_eff^(4/3), so the ratios need
    only the radii: tip–particle R_t R_p/(R_t + R_p), particle–substrate R_p, tip–substrate R_t.
    """
    rt = _check("tip_radius_nm", tip_radius_nm, lo=0.0, lo_open=True)
    rp = _check("particle_radius_nm", particle_radius_nm, lo=0.0, lo_open=True)
    f = _check("f_ts_a", f_ts_a, lo=0.0)
    return f * (rp / (rt + rp)) ** (4.0 / 3.0), f * (rp / rt) ** (4.0 / 3.0)


def rod_substrate_adhesion(f_ts_a, tip_radius_nm, rod_radius_nm, rod_length_nm,
                           work_of_adhesion, modulus_gpa):
    """F^a_os in nN of a rod lying on the substrate: F^a_ts · (2bL) / (πa_ts²), JKR areas."""
    b = jkr_contact_halfwidth(rod_radius_nm, work_of_adhesion, modulus_gpa)
    a = jkr_contact_radius(tip_radius_nm, work_of_adhesion, modulus_gpa)
    length = _check("rod_length_nm", rod_length_nm, lo=0.0, lo_open=True)
    return adhesion_from_area(f_ts_a, 2.0 * b * length, math.pi * a**2)


# --- kinematics ------------------------------------------------------------------------

def particle_step(x: float, y: float, diameter: float, tip_x: float, tip_y: float,
                  dx: float, dy: float, tip_radius: float = 0.0) -> tuple[float, float, bool]:
    """New particle centre (nm) after the tip moves by (dx, dy); returns (x, y, contact).

    Particles only translate (seed §4.2). With no tip–object friction (F^f_ot = 0) the
    push acts along the contact normal, so the particle slides along the line from the
    tip's end position through its centre until it touches the tip again (the tip slides
    round the particle). Steps should be shorter than the contact radius, or the tip can
    pass through a particle in one step.
    """
    rc = 0.5 * diameter + tip_radius
    if not (diameter > 0.0 and tip_radius >= 0.0 and math.isfinite(rc)):
        raise ValueError(f"diameter must be > 0 and tip_radius >= 0, got {diameter!r}, {tip_radius!r}")
    ex, ey = tip_x + dx, tip_y + dy
    gx, gy = x - ex, y - ey
    if not math.isfinite(gx + gy):
        raise ValueError("particle and tip positions and the step must be finite")
    gap = math.hypot(gx, gy)
    if gap >= rc:
        return x, y, False
    if gap == 0.0:                       # tip ends on the centre: push along the step
        gx, gy, gap = dx, dy, math.hypot(dx, dy)
        if gap == 0.0:
            return x, y, False
    k = rc / gap
    return ex + k * gx, ey + k * gy, True
