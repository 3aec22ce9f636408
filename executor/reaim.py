"""Re-aiming a planned push at where the object really is.

A plan's push was computed for the object at the pose the plan expected. When a local
scan finds it elsewhere, a particle is pushed straight from where it is to the push's
goal (the tip behind it on that line), and a rod's push is moved with the rigid motion
that takes the expected pose to the measured one.
"""

from __future__ import annotations

import math

from nanoasm.bodies import Body
from nanoasm.planner.plan import Expect, Operation

Point = tuple[float, float]


def particle_push(op: Operation, at: Point, radius: float, tip_radius: float,
                  lead: float = 0.0) -> Operation | None:
    """The push from ``at`` to ``op.expect.at``, the tip put down ``lead`` nm short of
    contact; None when already there (< 1 nm)."""
    gx, gy = op.expect.at
    d = math.dist(at, (gx, gy))
    if d < 1.0:
        return None
    ux, uy = (gx - at[0]) / d, (gy - at[1]) / d
    off = radius + tip_radius
    tip = ((at[0] - ux * (off + lead), at[1] - uy * (off + lead)), (gx - ux * off, gy - uy * off))
    return Operation(op.id, op.object, op.target, tip, op.expect, op.kind)


def rigid(expected: Body, measured: Body):
    """The rigid motion (a function of a point) taking ``expected`` onto ``measured``."""
    turn = math.remainder((measured.angle or 0.0) - (expected.angle or 0.0), 180.0)
    c, s = math.cos(math.radians(turn)), math.sin(math.radians(turn))
    ex, ey = expected.at
    mx, my = measured.at

    def move(p: Point) -> Point:
        dx, dy = p[0] - ex, p[1] - ey
        return (mx + c * dx - s * dy, my + s * dx + c * dy)

    return move, turn


def rod_push(op: Operation, expected: Body, measured: Body) -> Operation:
    """``op`` moved with the rod: the same push relative to the rod where it really is."""
    move, turn = rigid(expected, measured)
    angle = None if op.expect.angle is None else (op.expect.angle + turn) % 180.0
    return Operation(op.id, op.object, op.target, tuple(move(p) for p in op.tip_path),
                     Expect(move(op.expect.at), angle), op.kind)
