"""What an AFM tip records over simple bodies, in closed form.

The tip is a sphere of radius ``R`` on a cone of half angle ``α``; its apex is the
lowest point of the sphere. Scanning in contact, the apex traces the grey dilation of
the surface by the tip, ``z(x) = max_p h(p) − t(|p − x|)``, where ``t`` is the tip
profile (:func:`tip_profile`). For the bodies of a scene the dilation has a closed form:

- a ball of radius ``a`` resting on the substrate: dilating it by the tip gives the
  tip's shape grown by ``a`` (sphere of radius ``R + a``, same cone), so the apex
  height depends only on the lateral distance ``ρ`` to the ball's centre
  (:func:`ball_image`);
- a rod (capsule: a segment swept by a ball) is the union of balls along its core, so
  its image is :func:`ball_image` of the distance to the core segment;
- a flat plateau of height ``H`` with vertical walls: ``H − t(d)`` at distance ``d``
  from its footprint.

The renderer draws exact images with these functions and identification fits them.
Lengths in nm, angles in degrees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Tip:
    """A spherical tip of ``radius`` nm on a cone of ``half_angle`` degrees."""

    radius: float = 10.0
    half_angle: float = 20.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"radius must be positive and finite, got {self.radius}")
        if not (math.isfinite(self.half_angle) and 0 < self.half_angle < 90):
            raise ValueError(f"half_angle must be in (0, 90) degrees, got {self.half_angle}")


def _trig(half_angle: float) -> tuple[float, float, float]:
    alpha = math.radians(half_angle)
    return math.sin(alpha), math.cos(alpha), math.tan(alpha)


def tip_profile(rho: np.ndarray | float, tip: Tip) -> np.ndarray:
    """Height of the tip surface above its apex at lateral distance ``rho`` (any shape)."""
    rho = np.abs(np.asarray(rho, dtype=float))
    s, c, t = _trig(tip.half_angle)
    r = tip.radius
    rt = r * c
    sphere = r - np.sqrt(np.maximum(r * r - np.minimum(rho, rt) ** 2, 0.0))
    cone = r * (1 - s) + (rho - rt) / t
    return np.where(rho <= rt, sphere, cone)


def tip_reach(depth: np.ndarray | float, tip: Tip) -> np.ndarray:
    """Inverse of :func:`tip_profile`: lateral distance where the tip is ``depth`` above its apex."""
    depth = np.maximum(np.asarray(depth, dtype=float), 0.0)
    s, c, t = _trig(tip.half_angle)
    r = tip.radius
    zt = r * (1 - s)
    sphere = np.sqrt(np.maximum(r * r - (r - np.minimum(depth, zt)) ** 2, 0.0))
    cone = r * c + t * (depth - zt)
    return np.where(depth <= zt, sphere, cone)


def ball_image(rho: np.ndarray | float, a: np.ndarray | float, tip: Tip) -> np.ndarray:
    """Apex height over a ball of radius ``a`` resting on z = 0, at lateral distance ``rho``.

    ``2a`` over the centre, falling with ``rho``; it is negative beyond the ball's reach
    (the caller takes the maximum with the substrate). ``a = 0`` gives ``−tip_profile``.
    """
    rho = np.abs(np.asarray(rho, dtype=float))
    a = np.asarray(a, dtype=float)
    s, c, t = _trig(tip.half_angle)
    big = tip.radius + a                      # radius of the tip grown by the ball
    rt = big * c                              # where the grown sphere meets the cone
    sphere = np.sqrt(np.maximum(big * big - np.minimum(rho, rt) ** 2, 0.0))
    cone = big * s - (rho - rt) / t
    return a - tip.radius + np.where(rho <= rt, sphere, cone)


def ball_reach(a: np.ndarray | float, level: np.ndarray | float, tip: Tip) -> np.ndarray:
    """Inverse of :func:`ball_image`: the distance ``rho`` where the image is at ``level``.

    ``level`` below ``2a``; any level below zero is allowed (the cone continues).
    """
    a = np.asarray(a, dtype=float)
    level = np.minimum(np.asarray(level, dtype=float), 2 * a)
    s, c, t = _trig(tip.half_angle)
    big = tip.radius + a
    u = level - a + tip.radius                # height of the contact above the grown centre
    sphere = np.sqrt(np.maximum(big * big - u * u, 0.0))
    cone = big * c + t * (big * s - u)
    return np.where(u >= big * s, sphere, cone)


def plateau_image(dist: np.ndarray | float, height: float, tip: Tip) -> np.ndarray:
    """Apex height at distance ``dist`` from a flat plateau of ``height`` (0 inside it)."""
    return height - tip_profile(dist, tip)


def segment_distance(x: np.ndarray, y: np.ndarray, p: tuple[float, float],
                     q: tuple[float, float]) -> np.ndarray:
    """Distance of points ``(x, y)`` (broadcast together) to the segment from ``p`` to ``q``."""
    dx, dy = q[0] - p[0], q[1] - p[1]
    ux, uy = x - p[0], y - p[1]
    n2 = dx * dx + dy * dy
    if n2 == 0.0:
        return np.hypot(ux, uy)
    u = np.clip((ux * dx + uy * dy) / n2, 0.0, 1.0)
    return np.hypot(ux - u * dx, uy - u * dy)
