"""Rods pushed on a surface: pivot, minimum push force, tip–rod equilibrium, one step.

Seed §4.3 (eq. 4.8–4.20; eq. 4.13 as printed writes l + √(…) for l > L/2, which with
eq. 4.10 is l − √(…), and eq. 4.9 is s² − 2ls + lL − L²/2 = 0). A rod of length L (nm) pushed at the
point l (nm from its reference end A, 0 ≤ l ≤ L) with uniform substrate friction f per
unit length rotates about a pivot S on its axis at s from A (eq. 4.10); the pivot never
falls in ((1 − √2/2)L, (√2/2)L). l = L/2 is a bifurcation: the pivot jumps to either end,
chosen by ``branch`` (+1: the far end B, s = L, the limit l → L/2⁻; −1: the end A, s = 0).

In centred coordinates (u = l − L/2, pivot p = s − L/2, a = L/2) eq. 4.10 reads
p = −sgn(u)·a² / (√(u² + a²) + |u|), free of cancellation and never 0/0, and
ρ(l) = 2|p|/L = a / (√(u² + a²) + |u|) (eq. 4.13 with the errata, ρ(l) = ρ(L − l)).
Forces in nN, f in nN/nm, angles in degrees.
"""

from __future__ import annotations

import math
from enum import Enum
from typing import NamedTuple

import numpy as np

from .particle_push import (
    PushOutcome,
    min_normal_force,
    push_outcome,
    theta_max_deg,
    tip_object_repulsion,
)

#: Aspect ratios σ = L/d: below ROD_MAX_ASPECT a rod rotates rigidly (seed §4.3.1);
#: above FLEXIBLE_MIN_ASPECT it bends like a soft wire (Fig. 4.7); between, uncertain.
ROD_MAX_ASPECT = 15.0
FLEXIBLE_MIN_ASPECT = 25.0
#: Relative slack on the rod's half length, so a push exactly at an end survives rounding.
_END_SLACK = 1e-9


class Regime(str, Enum):
    """How an elongated object responds to a push (seed §4.3.1)."""

    RIGID = "rigid"          # σ < 15: the rod model of this module applies
    UNCERTAIN = "uncertain"  # 15 ≤ σ ≤ 25
    FLEXIBLE = "flexible"    # σ > 25: bends, not pushed as a rod


def aspect_regime(length: float, diameter: float) -> Regime:
    """Regime of a rod from its aspect ratio σ = L/d (seed §4.3.1, Fig. 4.7)."""
    if not (length > 0 and diameter > 0 and math.isfinite(length / diameter)):
        raise ValueError(f"length and diameter must be positive, got {length!r}, {diameter!r}")
    sigma = length / diameter
    if sigma < ROD_MAX_ASPECT:
        return Regime.RIGID
    return Regime.UNCERTAIN if sigma <= FLEXIBLE_MIN_ASPECT else Regime.FLEXIBLE


def _length(length) -> np.ndarray:
    L = np.asarray(length, dtype=float)
    if not np.all(np.isfinite(L)) or np.any(L <= 0):
        raise ValueError(f"length must be positive and finite, got {length!r}")
    return L


def _push_point(l, L: np.ndarray) -> np.ndarray:
    arr = np.asarray(l, dtype=float)
    if not np.all(np.isfinite(arr)) or np.any(arr < 0) or np.any(arr > L):
        raise ValueError(f"l must lie in [0, length], got {l!r}")
    return arr


def _branch(branch: int) -> int:
    if branch not in (-1, 1):
        raise ValueError(f"branch must be -1 or +1, got {branch!r}")
    return branch


def pivot_position(l, length, branch: int = 1):
    """Pivot s in nm from the reference end for a push at l (eq. 4.10, errata).

    s = l + √(l² − lL + L²/2) for l < L/2, l − √(…) for l > L/2; at l = L/2, s = L for
    ``branch`` +1 and 0 for −1. Vectorised over ``l``.
    """
    L = _length(length)
    l = _push_point(l, L)
    b, a = _branch(branch), 0.5 * L
    u = l - a
    sgn = np.where(u > 0, 1.0, np.where(u < 0, -1.0, -float(b)))
    return a - sgn * a * a / (np.hypot(u, a) + np.abs(u))


def rho(l, length):
    """ρ(l) = |2s/L − 1| of eq. 4.13 (errata): √2 − 1 at an end, 1 at the middle."""
    L = _length(length)
    u = _push_point(l, L) - 0.5 * L
    return 0.5 * L / (np.hypot(u, 0.5 * L) + np.abs(u))


def push_force_for_pivot(s, l, length, f):
    """Force in nN to push at l with the pivot at s inside the rod (eq. 4.8, magnitude).

    F = f((L − s)² + s²) / (2|l − s|); the pivot of eq. 4.10 minimises it over s.
    """
    L = _length(length)
    l, s = _push_point(l, L), _push_point(s, L)
    if np.any(s == l):
        raise ValueError("s must differ from l")
    return np.asarray(f, dtype=float) * ((L - s) ** 2 + s**2) / (2.0 * np.abs(l - s))


def min_push_force(l, length, f):
    """Minimum push force ρ(l)·fL in nN (eq. 4.12–4.14): (√2 − 1)fL at an end, fL mid-rod."""
    f = np.asarray(f, dtype=float)
    if not np.all(np.isfinite(f)) or np.any(f < 0):
        raise ValueError(f"f must be >= 0 (nN/nm), got {f!r}")
    return rho(l, length) * f * _length(length)


def rod_friction(mu_os, nu, f_os_r, f_os_a):
    """Total substrate friction fL = μos F^r_os + ν F^a_os in nN (before eq. 4.13)."""
    return (np.asarray(mu_os, dtype=float) * np.asarray(f_os_r, dtype=float)
            + np.asarray(nu, dtype=float) * np.asarray(f_os_a, dtype=float))


def rod_theta_max_deg(l, length, mu_os):
    """θmax = atan(1/(ρ μos)) in degrees for a rod pushed at l (after eq. 4.19)."""
    return theta_max_deg(mu_os, rho(l, length))


def rod_tip_repulsion(l, length, theta_deg, mu_os, nu, f_os_a, f_ot_a):
    """Tip–rod repulsion F^r_ot in nN (eq. 4.19); +inf if θ ≥ θmax."""
    return tip_object_repulsion(theta_deg, mu_os, nu, f_os_a, f_ot_a, rho(l, length))


def rod_min_normal_force(l, length, theta_deg, mu_os, nu, f_os_a, f_ts_a):
    """Minimum normal force F̄z in nN to keep the tip down on a rod (eq. 4.20, errata μos + ν)."""
    return min_normal_force(theta_deg, mu_os, nu, f_os_a, f_ts_a, rho(l, length))


def rod_push_outcome(f_z: float, l: float, length: float, theta_deg: float, mu_os: float,
                     nu: float, f_os_a: float, f_ts_a: float) -> PushOutcome:
    """Whether a push at l with normal force ``f_z`` (nN) turns the rod (eq. 4.19–4.20)."""
    return push_outcome(f_z, theta_deg, mu_os, nu, f_os_a, f_ts_a, float(rho(l, length)))


# --- kinematic step --------------------------------------------------------------------

class RodPose(NamedTuple):
    """Centre (x, y) in nm, axis angle in degrees, length and diameter in nm."""

    x: float
    y: float
    angle: float
    length: float
    diameter: float


class RodStep(NamedTuple):
    """Result of :func:`rod_step`: the new pose, whether the tip pushed, the pivot (nm)."""

    pose: RodPose
    contact: bool
    pivot: tuple[float, float] | None


def rod_step(pose: RodPose, tip: tuple[float, float], step: tuple[float, float], *,
             tip_radius: float = 0.0, branch: int = 1, pivot_offset: float = 0.0) -> RodStep:
    """Move the tip from ``tip`` by ``step`` (nm) against a rod; return its new pose.

    The rod is the seed's line segment (Fig. 4.8b) with contact distance d/2 + tip
    radius from its axis. If the tip ends within that distance of the side, the rod
    rotates about the pivot of eq. 4.10 for the contact point (u, centred) until the tip
    touches its side again; the contact point slides along the rod (no axial motion,
    §4.3.1). The tip leaves the rod once it is past an end (|u| > L/2, with 1e-9 relative
    slack); a tip entering through an end face slips over it (no contact). ``branch``
    picks the pivot at the bifurcation u = 0 exactly. The new angle is wrapped to
    [−180, 180). The pivot is that of the step's end point, so keep steps small
    against L (the result converges as the step shrinks).

    ``pivot_offset`` moves the pivot along the axis (toward +angle) by that fraction of
    L: a friction gradient along the rod (issue 14: 0.03 L for a gradient of about 60 %).
    The rotation is the model's; the rod turns about the moved pivot.
    """
    x, y, ang, L, d = pose
    if not (L > 0 and d > 0 and tip_radius >= 0):
        raise ValueError("length, diameter must be > 0 and tip_radius >= 0, "
                         f"got {L!r}, {d!r}, {tip_radius!r}")
    if branch not in (-1, 1):
        raise ValueError(f"branch must be -1 or +1, got {branch!r}")
    if not math.isfinite(x + y + ang + L + d + tip_radius + tip[0] + tip[1] + step[0] + step[1] + pivot_offset):
        raise ValueError("pose, tip and step must be finite")
    t = math.radians(ang)
    c, s = math.cos(t), math.sin(t)
    rx, ry = tip[0] - x, tip[1] - y
    u0, v0 = rx * c + ry * s, ry * c - rx * s
    u1 = u0 + step[0] * c + step[1] * s
    v1 = v0 + step[1] * c - step[0] * s
    half, rc = 0.5 * L, 0.5 * d + tip_radius
    reach = half * (1.0 + _END_SLACK)
    side = 1.0 if v0 > 0.0 else -1.0
    if abs(u1) > reach or v0 == 0.0 or side * v1 >= rc or (side * v0 < rc and abs(u0) > reach):
        return RodStep(RodPose(x, y, ang, L, d), False, None)
    sgn = 1.0 if u1 > 0.0 else (-1.0 if u1 < 0.0 else -float(branch))
    p = -sgn * half * half / (math.hypot(u1, half) + abs(u1))      # eq. 4.10, centred
    a, b = u1 - p, v1                                               # tip seen from the pivot
    r = math.hypot(a, b)                                            # ≥ (√2 − 1)L/2 > 0
    psi = math.atan2(b, a)
    target = math.asin(max(-1.0, min(1.0, side * rc / r)))
    if a < 0.0:                                                     # tip on the far side of S
        target = math.pi - target
    beta = math.remainder(psi - target, 2.0 * math.pi)             # rotation about the pivot
    t1 = t + beta
    c1, s1 = math.cos(t1), math.sin(t1)
    p += pivot_offset * L
    px, py = x + p * c, y + p * s
    angle = (ang + math.degrees(beta) + 180.0) % 360.0 - 180.0
    if angle >= 180.0:                                              # −tiny % 360 rounds to 360
        angle -= 360.0
    new = RodPose(x + p * (c - c1), y + p * (s - s1), angle, L, d)
    return RodStep(new, True, (px, py))
