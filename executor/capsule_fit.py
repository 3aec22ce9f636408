"""A rod's outline fitted to the edge crossings of its local scan lines.

Every edge crossing of a scan line with a rod lies on the rod's outline at the edge
level: a capsule around the rod's core. :func:`fit_capsule` fits that outline to all
the crossings of a pattern (:mod:`nanoasm.executor.rod_scan`) by least squares. Lengths
in nm, angles in degrees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares


@dataclass(frozen=True, eq=False)
class CapsuleFit:
    """A rod outline at the edge level: core segment of half-length ``half`` about
    ``centre`` at ``angle`` (deg), swept by a disc of radius ``radius``; ``cov`` (5, 5)
    over (x, y, angle [deg], half, radius), with the angle row zero when it was fixed."""

    centre: np.ndarray
    angle: float
    half: float
    radius: float
    cov: np.ndarray


def _unpack(params, angle, half):
    """(cx, cy, th, half, rad) from the free parameters; ``angle``/``half`` when fixed."""
    it = iter(params)
    cx, cy = next(it), next(it)
    th = next(it) if angle is None else angle
    hf = next(it) if half is None else half
    return cx, cy, th, hf, next(it)


def _capsule_residuals(params, pts, dirs, stds, angle, fixed_half=None):
    cx, cy, th, half, rad = _unpack(params, angle, fixed_half)
    a = np.array([math.cos(th), math.sin(th)])
    rel = pts - np.array([cx, cy])
    t = np.clip(rel @ a, -half, half)
    near = rel - t[:, None] * a
    dist = np.hypot(near[:, 0], near[:, 1])
    normal = near / np.maximum(dist, 1e-12)[:, None]
    along = np.maximum(np.abs(np.sum(normal * dirs, axis=1)), 0.1)
    return (dist - rad) / np.maximum(stds * along, 1e-3)


def fit_capsule(points, directions, stds, centre, angle: float, half: float, radius: float, *,
                fix_angle: bool = False, fix_half: bool = False) -> CapsuleFit | None:
    """Least-squares rod outline through edge crossings.

    Every edge crossing of a scan line with a rod lies on the rod's outline at the edge
    level: the points at one distance ``radius`` (the rod's half-width at that level,
    tip broadening included) from its core segment. Each crossing is uncertain along its
    own line, so its residual is weighted by its 1-σ times the cosine between the line
    and the outline's normal.

    Parameters
    ----------
    points : (k, 2) array
        Crossing points (nm).
    directions : (k, 2) array
        Unit directions of the lines they were found on.
    stds : (k,) array
        Their 1-σ along those lines (nm).
    centre, angle, half, radius
        Starting pose: centre (2,), axis angle (deg), core half-length and outline radius (nm).
    fix_angle : bool
        Keep ``angle`` (needs k >= 4); otherwise fit it (k >= 5).
    fix_half : bool
        Keep ``half`` (the believed length: one end of the rod was not seen); one
        crossing fewer is needed. Its row of ``cov`` is zero.

    Returns
    -------
    CapsuleFit, or None when the crossings do not determine the outline.
    """
    pts = np.asarray(points, float)
    dirs = np.asarray(directions, float)
    stds = np.asarray(stds, float)
    keep = [0, 1] + ([] if fix_angle else [2]) + ([] if fix_half else [3]) + [4]
    n_par = len(keep)
    if pts.shape[0] < n_par:
        return None
    th0 = math.radians(angle)
    x0 = [centre[0], centre[1], *([] if fix_angle else [th0]), *([] if fix_half else [max(half, 0.0)]),
          max(radius, 1e-3)]
    lower = [-np.inf, -np.inf, *([] if fix_angle else [-np.inf]), *([] if fix_half else [0.0]), 1e-6]
    fixed = th0 if fix_angle else None
    sol = least_squares(_capsule_residuals, x0, bounds=(lower, np.inf),
                        args=(pts, dirs, stds, fixed, max(half, 0.0) if fix_half else None),
                        x_scale="jac", method="trf")
    jac = sol.jac
    sv = np.linalg.svd(jac, compute_uv=False)
    if not (np.all(np.isfinite(sol.x)) and sv.size == n_par and sv[-1] > 1e-9 * sv[0]):
        return None
    try:
        cov_p = np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:     # singular despite the SVD test (rounding)
        return None
    cx, cy, th, hf, rad = _unpack(sol.x, fixed, max(half, 0.0) if fix_half else None)
    cov = np.zeros((5, 5))
    cov[np.ix_(keep, keep)] = cov_p
    conv = np.diag([1.0, 1.0, math.degrees(1.0), 1.0, 1.0])
    cov = conv @ cov @ conv
    if not np.all(np.isfinite(cov)):
        return None
    return CapsuleFit(np.array([cx, cy]), math.degrees(th), float(hf), float(rad), cov)


def near_angle(angle: float, reference: float) -> float:
    """``angle`` plus a multiple of 180° (a rod is symmetric), within 90° of ``reference``."""
    return reference + ((angle - reference + 90.0) % 180.0) - 90.0
