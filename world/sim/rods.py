"""One tip step against a rod or a wire: the new pose, from the seed's rod model and the
wire's local bending (pure functions; the bookkeeping is :mod:`nanoasm.world.sim.push`).

Rods (σ ≤ 25) turn by :func:`~nanoasm.world.pivot.rod_step`: the pivot of eq. 4.10 for the
contact point, the contact sliding along the rod, the tip leaving past an end. The truth
departs from the model in two ways:

- the object's own pivot offset (a fraction of its length along its axis, drawn once):
  the rotation angle of the model's step is applied about the shifted pivot;
- the bifurcation at l = L/2 (seed §4.3.1): within ``band`` × L of the
  middle the rod is stepped as if pushed exactly at its middle, where the pivot jumps to
  the end picked by the push's random ``branch``.

Wires (σ > 25) bend within the affecting region around the contact
(:mod:`nanoasm.world.sim.wire`); the contact point is put back at the contact distance
from the tip, as :func:`~nanoasm.world.particle_push.particle_step` does for a particle.
Lengths in nm, angles in degrees.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from nanoasm.bodies import Body
from nanoasm.world.pivot import RodPose, rod_step

from .wire import bend, closest_point



class RodMotion(NamedTuple):
    """The rod after a step (``None`` if the tip did not push it) and the push point l."""

    body: Body | None
    l: float
    pivot: tuple[float, float] | None


def axial(body: Body, p: tuple[float, float]) -> tuple[float, float]:
    """``(u, v)``: point ``p`` in the rod's frame (along the axis from the centre, across)."""
    t = math.radians(body.angle)
    c, s = math.cos(t), math.sin(t)
    rx, ry = p[0] - body.at[0], p[1] - body.at[1]
    return rx * c + ry * s, ry * c - rx * s


def rod_motion(body: Body, p0: tuple[float, float], p1: tuple[float, float], *, tip_radius: float,
               branch: int, pivot_offset: float, band: float = 0.02) -> RodMotion:
    """Step the tip from ``p0`` to ``p1`` against a rod; the rod's new pose if it turned."""
    L = body.length
    t = math.radians(body.angle)
    c, s = math.cos(t), math.sin(t)
    u1, _ = axial(body, p1)
    l = min(max(u1 + 0.5 * L, 0.0), L)
    shift = u1 if abs(u1) < band * L else 0.0
    pose = RodPose(body.at[0] + shift * c, body.at[1] + shift * s, body.angle, L, body.diameter)
    rs = rod_step(pose, p0, (p1[0] - p0[0], p1[1] - p0[1]), tip_radius=tip_radius, branch=branch)
    if not rs.contact:
        return RodMotion(None, l, None)
    beta = math.remainder(math.radians(rs.pose.angle - body.angle), 2.0 * math.pi)
    px = rs.pivot[0] + pivot_offset * L * c
    py = rs.pivot[1] + pivot_offset * L * s
    cb, sb = math.cos(beta), math.sin(beta)
    rx, ry = body.at[0] - px, body.at[1] - py
    centre = (float(px + cb * rx - sb * ry), float(py + sb * rx + cb * ry))
    angle = (body.angle + math.degrees(beta) + 180.0) % 360.0 - 180.0
    if angle >= 180.0:
        angle -= 360.0
    moved = Body(body.id, body.kind, centre, body.diameter, angle, L)
    return RodMotion(moved, l, (px, py))


def wire_motion(nodes: np.ndarray, diameter: float, p1: tuple[float, float], *, tip_radius: float,
                affect: float, step: tuple[float, float]) -> np.ndarray | None:
    """The wire's nodes after the tip arrives at ``p1``, or ``None`` if it does not touch.

    The nearest point of the wire is moved to the contact distance from the tip (along
    the line from the tip through it, or along ``step`` if the tip sits on the axis) and
    the wire bends within ``affect`` nm of it (:func:`~nanoasm.world.sim.wire.bend`).
    """
    rc = 0.5 * diameter + tip_radius
    k, f, dist = closest_point(nodes, p1)
    if dist >= rc:
        return None
    c = nodes[k] + f * (nodes[k + 1] - nodes[k])
    gx, gy = c[0] - p1[0], c[1] - p1[1]
    if dist == 0.0:
        gx, gy = step
        dist = math.hypot(gx, gy)
        if dist == 0.0:
            return None
    target = (p1[0] + rc * gx / dist, p1[1] + rc * gy / dist)
    return bend(nodes, k, f, (target[0] - c[0], target[1] - c[1]), affect)
