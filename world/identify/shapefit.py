"""Fitting the exact tip image of a ball or a capsule to the pixels of one object.

The model is :func:`~nanoasm.world.tipimage.ball_image` of the distance to the body's
core segment (a point for a particle), floored at the substrate (z = 0). Its free
parameters are the centre, the radius ``a`` (half the height, hence the diameter from
the height), for a capsule the axis angle and the core half-length, and the tip
radius: it is fitted too, so that real images taken with a blunter tip than nominal
still give unbiased heights and centres. The cone half angle is held fixed. The
Jacobians are analytic (the model is piecewise smooth: sphere and cone contact).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from nanoasm.world.tipimage import Tip, ball_image

#: Least and greatest tip radius (nm) the fit may use.
TIP_BOUNDS = (0.5, 500.0)


@dataclass(frozen=True)
class ShapeFit:
    """A fitted ball (``half_length`` 0) or capsule.

    ``centre`` (x, y) nm, ``angle`` degrees in [0, 180), ``half_length`` of the core
    segment, ``radius`` of the body, ``tip_radius`` fitted, ``rms`` residual (nm) over
    the ``pixels`` fitted, ``ok`` when the optimiser converged.
    """

    centre: tuple[float, float]
    angle: float
    half_length: float
    radius: float
    tip_radius: float
    rms: float
    ok: bool
    pixels: int

    @property
    def diameter(self) -> float:
        return 2 * self.radius

    @property
    def length(self) -> float:
        return 2 * (self.half_length + self.radius)


def _ball_image_grad(rho: np.ndarray, a: float, r: float, half_angle: float):
    """``max(ball_image, 0)`` and its derivatives by rho, a and the tip radius."""
    al = math.radians(half_angle)
    s, c, t = math.sin(al), math.cos(al), math.tan(al)
    big = r + a
    sphere = rho <= big * c
    root = np.sqrt(np.maximum(big * big - np.where(sphere, rho, 0.0) ** 2, 1e-12))
    shape = np.where(sphere, root, big * s - (rho - big * c) / t)
    value = a - r + shape
    d_rho = np.where(sphere, -rho / root, -1.0 / t)
    d_big = np.where(sphere, big / root, s + c / t)
    live = value > 0
    return (np.where(live, value, 0.0), np.where(live, d_rho, 0.0),
            np.where(live, 1.0 + d_big, 0.0), np.where(live, -1.0 + d_big, 0.0))


def _capsule_parts(p: np.ndarray, x: np.ndarray, y: np.ndarray):
    x0, y0, th, hl = p[:4]
    c, s = math.cos(th), math.sin(th)
    dx, dy = x - x0, y - y0
    u = dx * c + dy * s                              # along the axis
    v = -dx * s + dy * c                             # across it
    past = np.abs(u) > hl
    along = np.where(past, np.abs(u) - hl, 0.0)
    rho = np.hypot(along, v)
    return c, s, u, v, past, along, rho


def capsule_model(p: np.ndarray, x: np.ndarray, y: np.ndarray, half_angle: float) -> np.ndarray:
    """Image heights for parameters ``p = (x0, y0, theta[rad], half_length, a, tip_radius)``."""
    *_, rho = _capsule_parts(p, x, y)
    return np.maximum(ball_image(rho, p[4], Tip(p[5], half_angle)), 0.0)


def _capsule_jac(p: np.ndarray, x: np.ndarray, y: np.ndarray, half_angle: float) -> np.ndarray:
    c, s, u, v, past, along, rho = _capsule_parts(p, x, y)
    _, d_rho, d_a, d_r = _ball_image_grad(rho, p[4], p[5], half_angle)
    safe = np.where(rho > 0, rho, 1.0)
    g_along = np.where(rho > 0, along / safe, 0.0) * d_rho      # dz / d(along)
    g_v = np.where(rho > 0, v / safe, 0.0) * d_rho              # dz / dv
    sgn = np.where(past, np.sign(u), 0.0)
    g_u = g_along * sgn                                          # dz / du
    jac = np.empty((x.size, 6))
    jac[:, 0] = g_u * -c + g_v * s                               # du/dx0 = -c, dv/dx0 = s
    jac[:, 1] = g_u * -s + g_v * -c
    jac[:, 2] = g_u * v + g_v * -u                               # du/dth = v, dv/dth = -u
    jac[:, 3] = -g_along * past
    jac[:, 4] = d_a
    jac[:, 5] = d_r
    return jac


def ball_model(p: np.ndarray, x: np.ndarray, y: np.ndarray, half_angle: float) -> np.ndarray:
    """Image heights for parameters ``p = (x0, y0, a, tip_radius)``."""
    x0, y0, a, r = p
    return np.maximum(ball_image(np.hypot(x - x0, y - y0), a, Tip(r, half_angle)), 0.0)


def _ball_jac(p: np.ndarray, x: np.ndarray, y: np.ndarray, half_angle: float) -> np.ndarray:
    x0, y0, a, r = p
    dx, dy = x - x0, y - y0
    rho = np.hypot(dx, dy)
    _, d_rho, d_a, d_r = _ball_image_grad(rho, a, r, half_angle)
    safe = np.where(rho > 0, rho, 1.0)
    jac = np.empty((x.size, 4))
    jac[:, 0] = np.where(rho > 0, -dx / safe, 0.0) * d_rho
    jac[:, 1] = np.where(rho > 0, -dy / safe, 0.0) * d_rho
    jac[:, 2] = d_a
    jac[:, 3] = d_r
    return jac


def _check(x: np.ndarray, y: np.ndarray, z: np.ndarray, n_params: int) -> None:
    if not (x.shape == y.shape == z.shape and x.ndim == 1):
        raise ValueError("x, y and z must be 1-D arrays of one length")
    if x.size <= n_params:
        raise ValueError(f"need more than {n_params} pixels to fit, got {x.size}")


def _solve(model, jac, p0, lo, hi, x, y, z, half_angle, scale):
    p0 = np.clip(p0, lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))
    res = least_squares(lambda p: model(p, x, y, half_angle) - z, p0,
                        jac=lambda p: jac(p, x, y, half_angle), bounds=(lo, hi),
                        x_scale=scale, method="trf", xtol=1e-9, ftol=1e-9, max_nfev=200)
    return res.x, float(np.sqrt(np.mean(res.fun ** 2))), bool(res.success)


def fit_ball(x: np.ndarray, y: np.ndarray, z: np.ndarray, *, centre: tuple[float, float],
             radius: float, tip: Tip, reach: float) -> ShapeFit:
    """Fit a ball's image to pixels ``(x, y, z)`` (1-D, nm) from a first guess.

    ``reach`` (nm) bounds how far the centre may move from the guess.
    """
    _check(x, y, z, 4)
    p0 = np.array([centre[0], centre[1], radius, tip.radius])
    lo = np.array([centre[0] - reach, centre[1] - reach, 0.05 * radius, TIP_BOUNDS[0]])
    hi = np.array([centre[0] + reach, centre[1] + reach, 4.0 * radius + 1.0, TIP_BOUNDS[1]])
    (x0, y0, a, r), rms, ok = _solve(ball_model, _ball_jac, p0, lo, hi, x, y, z, tip.half_angle,
                                     np.ones(4))
    return ShapeFit((float(x0), float(y0)), 0.0, 0.0, float(a), float(r), rms, ok, x.size)


def fit_capsule(x: np.ndarray, y: np.ndarray, z: np.ndarray, *, centre: tuple[float, float],
                angle: float, half_length: float, radius: float, tip: Tip,
                reach: float) -> ShapeFit:
    """Fit a capsule's image to pixels ``(x, y, z)`` (1-D, nm) from a first guess.

    ``angle`` in degrees; ``reach`` (nm) bounds the centre's move and the half length.
    """
    _check(x, y, z, 6)
    th = math.radians(angle)
    p0 = np.array([centre[0], centre[1], th, half_length, radius, tip.radius])
    lo = np.array([centre[0] - reach, centre[1] - reach, th - math.pi / 2, 0.0,
                   0.05 * radius, TIP_BOUNDS[0]])
    hi = np.array([centre[0] + reach, centre[1] + reach, th + math.pi / 2,
                   half_length + reach, 4.0 * radius + 1.0, TIP_BOUNDS[1]])
    scale = np.array([1.0, 1.0, 1.0 / max(half_length + radius, 1.0), 1.0, 1.0, 1.0])
    (x0, y0, th, hl, a, r), rms, ok = _solve(capsule_model, _capsule_jac, p0, lo, hi, x, y, z,
                                             tip.half_angle, scale)
    return ShapeFit((float(x0), float(y0)), math.degrees(th) % 180.0, float(hl), float(a),
                    float(r), rms, ok, x.size)
