"""Where a pushed object sits on the tip, from the lever's signals (seed ch. 3, eq. 3.5-3.12).

The object pushes back on the tip along the contact normal (no tip–object friction, the
seed's F^f_ot = 0): from a particle's centre to the tip, from a rod's axis to the tip.
The *contact angle* is the signed angle (degrees) from the push direction ``u`` to the
direction from the tip to the object, positive when the object sits to the left of the
push line (counter-clockwise of ``u``, AFM frame). A particle of radius R on a tip of
radius r_tip sits ``(R + r_tip) sin(angle)`` off the tip's line; the tip keeps carrying it
while ``|angle|`` stays within the capture cone (``[sim] capture_angle``, the 45° of
:mod:`nanoasm.executor.push_legs`). For a rod pushed across its axis the angle is how far
the rod's surface normal at the contact turns from the push.

The seed's 3-D force (eq. 3.8-3.11) assumes the lateral force opposes the motion, so it
cannot see the side an object sits on. Here both components are measured, in the
cantilever frame (eq. 3.7): F_y = (k_l K_l / h) S̄_l (eq. 3.9), and F_x from the normal
signal, eq. 3.5-3.6 read the other way: F_x = (l / h)(k K_n S̄_n − F_z). The lever's
normal load F_z is not known to the fraction of a nanonewton this needs (a nanometre of
substrate height is 0.12 nN, 8 nN of F_x), so S̄_n is taken relative to ``sn_free``, the
S̄_n of the tip sliding free on the substrate along the same line just before it met the
object, when F_x was the friction's alone. The lateral force goes to the AFM frame by
R(ψ)⁻¹ (eq. 3.12); adding back the tip–substrate friction along the motion leaves the
object's force. F_x is (l/h) = 67 times noisier than F_y, so the angle is precise where
the object's side shows in F_y (a push along the lever's axis, φ near 0 or 180°) and
coarse where it shows only in F_x (a push across the lever).

Units: signals in V, forces in nN, angles in degrees. The std is the first-order
propagation of the detector noise (independent per sample on S_n and S_l, through the
cross-talk compensation of eq. 3.28); a reference measured over ``free_samples`` adds its
own noise, common to every sample it serves.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nanoasm.param import number
from nanoasm.world.cantilever import SEED_LEVER, Cantilever, scan_rotation


@dataclass(frozen=True)
class ContactAngle:
    """Per sample (or per mean of samples): ``angle`` and its 1σ ``std`` (degrees), the
    object's horizontal force on the tip ``force`` (nN) and that force ``vector`` ``(..., 2)``
    (nN, AFM frame). NaN where a signal saturates."""

    angle: np.ndarray
    std: np.ndarray
    force: np.ndarray
    vector: np.ndarray


def substrate_friction(preload: float, lever: Cantilever = SEED_LEVER, mu_ts: float = 0.086,
                       adhesion: float = 0.0) -> float:
    """Tip–substrate friction μts (F_z + F^a_ts) in nN for a ``preload`` (nm) deflection,
    μts from the friction loop (seed §3.4.3) and the adhesion F^a_ts (nN) from a force curve."""
    for name, v in (("preload", preload), ("mu_ts", mu_ts), ("adhesion", adhesion)):
        number(name, v, nonnegative=True)
    return mu_ts * (lever.spring_constant * preload + adhesion)


def _unit(direction) -> np.ndarray:
    u = np.asarray(direction, float)
    if u.shape[-1:] != (2,) or not np.all(np.isfinite(u)):
        raise ValueError(f"direction must be finite (..., 2) vectors, got shape {u.shape}")
    n = np.hypot(u[..., 0], u[..., 1])
    if np.any(n == 0):
        raise ValueError("direction must not be a zero vector")
    return u / n[..., None]


def contact_angle(sn_bar, sl_bar, direction, psi: float, lever: Cantilever = SEED_LEVER, *,
                  sn_free: float, noise_rms: float, friction: float = 0.0, sl_free: float | None = None,
                  relief: float = 0.0, samples: int = 1, free_samples: int = 0) -> ContactAngle:
    """The contact angle of the object the tip pushes along ``direction``.

    Parameters
    ----------
    sn_bar, sl_bar : array
        Compensated signals S̄_n, S̄_l (V, eq. 3.28) while pushing; each the mean of
        ``samples`` samples.
    direction : (2,) or (..., 2) array
        The push direction in the AFM (scanner) frame; any length.
    psi : float
        Scan angle ψ (degrees) of R(ψ), eq. 3.7.
    lever : Cantilever
        The executor's lever: k, K_n, k_l K_l / h, h, l and the cross-talk α.
    sn_free : float
        S̄_n (V) of the tip sliding free on the substrate along ``direction`` with the same
        preload, before it met the object: the level against which F_x is measured.
    noise_rms : float
        Detector noise per sample on S_n and S_l (V), e.g. the spread of the free-air
        baseline.
    friction : float
        The tip–substrate friction (nN) against the motion, e.g.
        :func:`substrate_friction`. Subtracted from the lateral force; with ``sl_free``
        it is measured instead and this value cancels.
    sl_free : float, optional
        S̄_l (V) of the same free slide: the friction's and any compensation error's part
        of S̄_l, measured.
    relief : float
        μts tan θ (θ = θx + γ, eq. 4.1): the friction the object's lift F^r_to sin θ
        takes off the substrate per nN of contact force (eq. 4.3-4.4), which the free
        slide did not have; 0.086 tan 20° = 0.031 for the seed's tip. 0 leaves angles
        that much steeper, ``atan(sin a / (cos a − relief))``.
    samples, free_samples : int
        How many samples each signal and the free-slide references are means of;
        ``free_samples`` 0 takes the references as exact.

    Returns
    -------
    ContactAngle
    """
    number("noise_rms", noise_rms, nonnegative=True)
    number("friction", friction)
    number("sn_free", sn_free)
    number("relief", relief, nonnegative=True, hi=0.5)
    if not (isinstance(samples, (int, np.integer)) and samples >= 1):
        raise ValueError(f"samples must be a positive integer, got {samples!r}")
    if not (isinstance(free_samples, (int, np.integer)) and free_samples >= 0):
        raise ValueError(f"free_samples must be a non-negative integer, got {free_samples!r}")
    u = _unit(direction)
    v = np.stack([-u[..., 1], u[..., 0]], axis=-1)     # to the left of the push line
    sn, sl = np.broadcast_arrays(np.asarray(sn_bar, float), np.asarray(sl_bar, float))
    r2 = scan_rotation(psi)[:2, :2]                    # v_cantilever = R v_AFM (eq. 3.7)
    gains = np.array([lever.lever_length / lever.tip_height * lever.spring_constant * lever.normal_gain,
                      lever.lateral_gain])             # nN/V of F_x (eq. 3.5-3.6) and F_y (eq. 3.9)
    f_x = gains[0] * (sn - sn_free)                    # F_x less the free slide's friction part
    if sl_free is None:                                # F_y less the expected friction's part
        f_y = gains[1] * sl + friction * (u @ r2.T)[..., 1]
    else:
        f_y = gains[1] * (sl - sl_free)
    force = np.stack([f_x, f_y], axis=-1) @ r2         # R⁻¹ = Rᵀ (eq. 3.12): the object's force
    p = -np.sum(force * v, axis=-1)                    # c sin(angle)
    q = -np.sum(force * u, axis=-1)                    # c cos(angle), less the lift's relief
    q = q + relief * np.hypot(p, q)
    c2 = p * p + q * q
    # d angle / d(S̄_n, S̄_l): d angle / d force (AFM frame), back through R and the gains
    g = ((p[..., None] * u - q[..., None] * v) / np.where(c2 > 0, c2, np.inf)[..., None]) @ r2.T * gains
    var = _noise(g[..., 0], g[..., 1], noise_rms, lever.crosstalk) / samples
    if free_samples:
        var = var + _noise(g[..., 0], g[..., 1] if sl_free is not None else 0.0, noise_rms,
                           lever.crosstalk) / free_samples
    bad = (np.abs(sn) >= lever.full_scale) | (np.abs(sl) >= lever.full_scale)
    angle = np.where(bad, np.nan, np.degrees(np.arctan2(p, q)))
    std = np.where(bad, np.nan, np.degrees(np.sqrt(var)))
    return ContactAngle(angle, std, np.sqrt(c2), -(p[..., None] * v + q[..., None] * u))


def _noise(gn, gl, sigma: float, alpha: float):
    """Variance of ``gn S̄_n + gl S̄_l`` for detector noise ``sigma`` on S_n and S_l, each
    sample: S̄_l = S_l − B − α S̄_n carries −α times S̄_n's noise (eq. 3.28)."""
    return sigma ** 2 * ((gn - alpha * gl) ** 2 + gl ** 2)


def offset_from_angle(angle_deg, radius: float, tip_radius: float) -> np.ndarray:
    """How far (nm) a particle of ``radius`` sits off the line of a tip of ``tip_radius``
    at a contact angle (degrees): ``(R + r_tip) sin(angle)``, positive to the left."""
    return (radius + tip_radius) * np.sin(np.radians(np.asarray(angle_deg, float)))


def capture_margin(angle_deg, capture_angle: float = 45.0) -> np.ndarray:
    """Degrees left before the contact normal leaves the capture cone (negative: outside)."""
    if not 0.0 < capture_angle < 90.0:
        raise ValueError(f"capture_angle must lie in (0, 90), got {capture_angle!r}")
    return capture_angle - np.abs(np.asarray(angle_deg, float))


__all__ = ["ContactAngle", "capture_margin", "contact_angle", "offset_from_angle", "substrate_friction"]
